"""A PSF measured too large: its lost edge fitted from a video, and the second fit through it (issue 39).

The bundle here is simulated with one PSF crop and handed the PSF of a crop 5 % smaller (the same
caustic magnified, rendered from the source image), so the handed PSF lost the ring that fell off
the sensor, as a real calibration's would."""

from dataclasses import replace

import h5py
import numpy as np
import pytest
import torch

from rngcam.formats.bundle import read_bundle
from rngcam.physics.operators import RollingShutter
from rngcam.physics.psf import magnify
from rngcam.recon import checkpoint, misfit
from rngcam.recon.methods import psf_edge
from rngcam.recon.methods.psf_edge import edge_mask, fit_edge, search_edge
from rngcam.recon.methods.stfm.edge_refit import EdgeRefit, edge_line, edge_scale
from rngcam.recon.methods.stfm.stage_configs import EdgeRefitConfig
from rngcam.recon.methods.stfm.subframes import SubframesAveraged
from rngcam.recon.problem import build_problem
from rngcam.sim.simulate import DEFAULT_PSF_CROP, simulate

LARGE = 1.05


@pytest.fixture(scope="module")
def problems(tmp_path_factory):
    """(the problem with the PSF 5 % too large, the same capture with its own PSF), 32 px, fine."""
    folder = tmp_path_factory.mktemp("edge")
    data, other, wrong = folder / "matched.h5", folder / "other.h5", folder / "wrong.h5"
    simulate("sineball", data, size=32, fidelity="fine")
    simulate("sineball", other, size=32, fidelity="fine", psf_crop=DEFAULT_PSF_CROP / LARGE)
    with h5py.File(other, "r") as f:
        psf = f["calibration/psf"][()]
    wrong.write_bytes(data.read_bytes())
    with h5py.File(wrong, "r+") as f:
        f["calibration/psf"][...] = psf
    return build_problem(read_bundle(wrong)), build_problem(read_bundle(data))


def _residual(problem, psf) -> float:
    p = problem.to(torch.float64)
    pred = RollingShutter(psf.double(), p.rs_weights, p.b_rs.shape[-1], channels=p.channels).A(p.truth)
    return float((pred - p.b_rs).norm() / p.b_rs.norm())


def test_the_edge_is_what_a_shrunk_psf_does_not_cover_and_its_neighbours():
    assert not edge_mask((16, 20), 1.0).any()
    mask = edge_mask((16, 20), 0.9)
    covered = magnify(np.ones((1, 16, 20)), 0.9)[0]
    covered /= covered.max()
    short = covered < 1 - 1e-9
    grown = short.copy()  # a binned pixel gathers sensor light up to one grid pixel past its square
    grown[1:] |= short[:-1]
    grown[:-1] |= short[1:]
    grown[:, 1:] |= short[:, :-1]
    grown[:, :-1] |= short[:, 1:]
    assert np.array_equal(mask, grown)
    assert mask[:2].all() and mask[:, -2:].all() and not mask[4:-4, 4:-4].any()


def test_the_lost_edge_is_fitted_from_the_true_video(problems):
    wrong, matched = problems
    found = fit_edge(wrong, wrong.truth, 1 / LARGE)
    mask = edge_mask(tuple(wrong.psf.shape[-2:]), 1 / LARGE)
    assert found["edge_pixels"] == mask.sum() and found["rows"] == wrong.b_rs.shape[1]
    assert torch.allclose(found["psf"].double().sum((1, 2)), torch.ones(3, dtype=torch.float64), atol=1e-6)
    assert (found["psf"] >= 0).all()
    # the edge holds about the energy the true PSF has there, and the data are explained nearly as
    # well as by it (the true grid PSF is exact here: physics.psf.bin_psf; the fit's free edge pixels
    # take up some noise, which the normalisation to one then costs)
    true_energy = matched.psf.double()[:, mask].sum(1)
    assert np.allclose(found["psf"].double()[:, mask].sum(1).numpy(), true_energy.numpy(), rtol=0.15)
    assert 0 < min(found["edge_energy"]) and max(found["edge_energy"]) < true_energy.max()
    assert found["residual"] < 0.5 * found["residual_shrunk"]
    assert _residual(wrong, found["psf"]) < 1.1 * _residual(wrong, matched.psf)
    assert _residual(wrong, wrong.psf) > 2 * _residual(wrong, found["psf"])


def test_the_shrink_is_searched_with_the_edge_fitted(problems):
    wrong, _ = problems
    found = search_edge(wrong, wrong.truth)
    assert found["scale"] == pytest.approx(1 / LARGE, abs=0.03)
    assert found["residual"] == min(r for _, r in found["searched"])
    assert fit_edge(wrong, wrong.truth, 1.0) is None  # nothing lost at the handed scale
    assert fit_edge(wrong, wrong.truth * float("nan"), 0.95) is None  # a video gone bad fits nothing


def test_rows_beyond_the_design_limit_are_subsampled(problems, monkeypatch):
    wrong, _ = problems
    whole = fit_edge(wrong, wrong.truth, 1 / LARGE)
    pixels = int(edge_mask(tuple(wrong.psf.shape[-2:]), 1 / LARGE).sum())
    # 32 px has too few rows for 4 RS pixels per unknown in half of them: ask for 2 here
    monkeypatch.setattr(psf_edge, "MIN_EQUATIONS", 2)
    monkeypatch.setattr(psf_edge, "MAX_DESIGN", 32 * pixels * 16)
    found = fit_edge(wrong, wrong.truth, 1 / LARGE)
    assert found["rows"] == 16  # of 32: the PSF fitted on them explains all rows nearly as well
    assert _residual(wrong, found["psf"]) < 1.25 * _residual(wrong, whole["psf"]) < 0.6 * _residual(wrong, wrong.psf)
    monkeypatch.setattr(psf_edge, "MAX_DESIGN", 32 * pixels * 2)  # 4 rows: fewer RS pixels than 2 per unknown
    assert fit_edge(wrong, wrong.truth, 1 / LARGE) is None and search_edge(wrong, wrong.truth) is None


class _Fit:
    """A stand-in for a whole STFM run: stops after one step with a given residual and video."""

    def __init__(self, residual, video, noise=0.01):
        self.rs, self.video, self.rs_noise_level = residual, video, noise
        self.supports_holdout = self.stops_itself = True
        self.left_out, self.notes, self.steps, self.asked = [], ["a note"], 0, 0

    def step(self):
        self.steps += 1
        return 0.0

    def converged(self):
        return "stalled" if self.steps else None

    def log_ready(self):
        return True

    def residuals(self):
        self.asked += 1
        return {"rs": self.rs}

    def estimate(self):
        return self.video

    def state_dict(self):
        return {"steps": self.steps}

    def load_state_dict(self, state):
        self.steps = state["steps"]

    def resolved_settings(self):
        return {"self_calibration": {"mode": "gains"}}


def _refit(problem, first_rs, later_rs, config=None):
    """An EdgeRefit over stand-ins whose fits through fitted edges end on `later_rs` in turn."""
    made = []

    def another(psf, report):
        made.append((psf, report))
        return _Fit(later_rs[len(made) - 1], problem.truth)

    return EdgeRefit(_Fit(first_rs, problem.truth), problem, 0.97, another, config), made


def _through_checkpoint(method, folder, iteration: int = 1) -> dict:
    """`method`'s state as a run's checkpoint file saves it and a resumed run loads it."""
    checkpoint.save(folder / "c.pt", {"method": method.state_dict(), "iteration": iteration, "solve_s": 1.0,
                                      "wall_s": 1.0, "log": [], "events": [], "rng": torch.get_rng_state(),
                                      "identity": None})
    return checkpoint.load(folder / "c.pt")["method"]


def _run(method, limit=10):
    for _ in range(limit):
        method.step()
        if method.converged():
            return


@pytest.mark.parametrize("later, kept", [((0.0105,), 1), ((0.05,), 0), ((0.02, 0.0105), 2), ((0.02, 0.025), 1)])
def test_a_fit_left_unexplained_is_fitted_again_through_the_edge(problems, later, kept):
    wrong, _ = problems
    method, made = _refit(wrong, 0.03, later)
    assert method.notes == ["a note"]  # nothing said before it is tried
    method.step()
    assert method.converged() is None and len(made) == 1  # the second fit starts
    assert method.residuals()["rs"] == min(later[0], 0.03)  # the running fit shown where it does better
    _run(method)
    report = method.report
    assert len(made) == len(later) and report["kept"] == kept
    assert method.residuals()["rs"] == ([0.03] + list(later))[kept]
    assert all(r["scale"] == pytest.approx(1 / LARGE, abs=0.03) for r in report["refits"])
    assert [r["rs"] for r in report["refits"]] == list(later)
    if len(later) == 2:  # the third fit's edge came from the best fit's video
        assert report["refits"][1]["from_fit"] == 1
    if kept == 0:  # the first fit's video gave its edge: not fitted again
        assert "did not do better" in report["why"]
    line = method.notes[-1]
    assert line.startswith("PSF edge (") and ["the first", "the second", "the third"][kept] + " fit kept" in line
    assert method.stops_itself and method.supports_holdout  # asked of it after every step, whichever fit is left
    out = method.resolved_settings()
    assert out["edge_refits"]["kept"] == kept and out["self_calibration"]["psf_edge"]["kept"] == kept
    assert out["psf_edge"] is True  # the setting, as the run had it


def test_an_edge_that_pays_too_little_is_reported_with_its_scale_and_not_fitted_through(problems):
    wrong, _ = problems
    edge = search_edge(wrong, wrong.truth)["residual"]
    first_rs = edge / 0.95  # the edge would lower the first fit's residual by 5 %, under EDGE_MIN_DROP
    made = []
    method = EdgeRefit(_Fit(first_rs, wrong.truth, noise=first_rs / 1.3), wrong, 0.97,
                       lambda psf, report: made.append(psf))
    _run(method)
    report = method.report
    assert made == [] and report["kept"] == 0 and report["refits"] == []
    found = report["not_refitted"]
    assert found["scale"] == pytest.approx(1 / LARGE, abs=0.03) and found["drop"] == pytest.approx(0.05, abs=0.01)
    assert f"(x{found['scale']:.4f}) lowers its RS residual by 5.0 %" in report["why"]
    assert report["why"] in method.notes[-1]


def test_the_refits_are_bounded(problems):
    wrong, _ = problems
    method, made = _refit(wrong, 0.03, (0.029, 0.028, 0.027))
    _run(method)
    assert len(made) == EdgeRefitConfig().max_refits and method.report["kept"] == 2
    assert method.report["why"] == f"{EdgeRefitConfig().max_refits} fits through a fitted edge made"


@pytest.mark.parametrize("running_rs, shown", [(0.05, 0.03), (0.02, 0.02)])
def test_a_later_fit_cut_short_is_shown_only_where_it_does_better(problems, running_rs, shown):
    wrong, _ = problems
    method, made = _refit(wrong, 0.03, (running_rs,))
    method.step()
    assert method.converged() is None and len(made) == 1  # the loop ends here (a budget): no own stop
    assert method.residuals()["rs"] == shown and method.estimate() is wrong.truth
    kept = 0 if shown == 0.03 else 1
    assert method.resolved_settings()["edge_refits"]["kept"] == kept
    assert "(not run to its own stop)" in method.notes[-1]
    assert f"the {['first', 'second'][kept]} fit kept" in method.notes[-1]
    assert method._fits[1].asked == 1  # the running fit's residual worked out once a step, however often asked


def test_a_run_resumed_in_a_later_fit_makes_that_fit_again(problems, tmp_path):
    wrong, _ = problems
    method, made = _refit(wrong, 0.03, (0.0105,))
    method.step()
    method.converged()
    state = _through_checkpoint(method, tmp_path)
    again, made_again = _refit(wrong, 0.03, (0.0105,))
    again.load_state_dict(state)
    assert len(made_again) == 1 and torch.equal(made_again[0][0], made[0][0])
    assert again.residuals()["rs"] == 0.0105 and again.report["refits"][0]["scale"] == method.report["refits"][0]["scale"]
    _run(again)
    assert again.report["kept"] == 1
    from rngcam.errors import RngcamError

    for bad in ({"edge_made": {1: state["edge_made"][1][:, :4]}}, {"edge_current": 7}, {"edge_made": {}}):
        with pytest.raises(RngcamError, match="PSF-edge stage is not as rngcam writes it"):
            _refit(wrong, 0.03, (0.0105,))[0].load_state_dict({**state, **bad})


def test_a_run_resumed_after_a_later_fit_did_better_than_the_first_resumes(problems, tmp_path):
    """The first fit is let go once a later one does better: a checkpoint written in the third fit
    holds the second and the third, and resumes there (a resumed run once refused it)."""
    wrong, _ = problems
    method, _ = _refit(wrong, 0.03, (0.02, 0.0105))
    for _ in range(2):
        method.step()
        method.converged()
    assert method._current == 2 and sorted(method._fits) == [1, 2]
    state = _through_checkpoint(method, tmp_path, 2)
    again, made = _refit(wrong, 0.03, (0.02, 0.0105))
    again.load_state_dict(state)
    assert len(made) == 2 and sorted(again._fits) == [1, 2] and again.residuals()["rs"] == 0.0105  # the running fit does better
    _run(again)
    assert again.report["kept"] == 2 and again.residuals()["rs"] == 0.0105


def test_no_second_fit_where_the_first_explains_the_data(problems):
    wrong, _ = problems
    method, made = _refit(wrong, 0.0105, (0.001,))
    _run(method)
    assert not made and method.report["kept"] == 0
    assert "within 1.15x its noise level" in method.notes[-1] and method.notes[-1].startswith("PSF edge not fitted")


def test_no_second_fit_where_the_edge_does_not_pay(problems):
    wrong, _ = problems
    method, made = _refit(wrong, 0.03, (0.001,), EdgeRefitConfig(min_drop=0.999))
    _run(method)
    assert not made
    assert "(< 99.9 %)" in edge_line(method.report)


def test_the_edge_is_tried_only_where_the_key_rows_find_the_psf_too_large():
    def report(estimate, applied=False):
        return {"scales": {"psf": {"estimate": estimate, "applied": applied}}}

    assert edge_scale(report(0.97)) == 0.97
    assert edge_scale(report(0.995)) is None and edge_scale(report(1.05, True)) is None
    assert edge_scale(None) is None and edge_scale({"scales": {"psf": {"estimate": "x"}}}) is None


def test_the_verdict_names_the_shrink_the_output_was_fitted_through():
    base = {"applied": True, "scales": {"psf": {"estimate": 0.978, "applied": False, "why": "x"}}}
    said = misfit.verdict(0.03, 0.01, dict(base, psf_edge={"scale": 0.9513, "kept": 1}))
    assert "PSF scale (x0.951 with its lost edge fitted" in said["line"] and said["threshold"] == misfit.MISFIT_RATIO
    kept_first = misfit.verdict(0.03, 0.01, dict(base, psf_edge={"scale": None, "kept": 0}))
    assert kept_first["likely_causes"][0] == "PSF scale" and kept_first["threshold"] == misfit.POINTED_RATIO


def test_stfm_is_wrapped_only_where_the_key_rows_find_the_psf_too_large(problems):
    from rngcam.recon.methods.stfm.recipe import make_stfm
    from rngcam.recon.methods.stfm.settings import STFMSettings

    wrong, matched = problems
    settings = STFMSettings(self_calibrate="gains", preset="prior", row_gain_refit=False, track_refit=False)  # their own tests
    whole = make_stfm(wrong, settings)
    assert isinstance(whole, SubframesAveraged)  # the prior preset's half-frames around every stage
    method = whole._method
    assert isinstance(method, EdgeRefit)
    assert method.report["key_rows_scale"] < 0.99
    second = method._make_refit(wrong.psf * 0 + 1 / wrong.psf[0].numel(), {"scale": 0.95})
    assert not isinstance(second, (EdgeRefit, SubframesAveraged))  # one second fit, never a third
    assert second.problem.shape[1] == 2 * wrong.shape[1]  # on the run's half-frames, not subdivided again
    assert second.state.selfcal_report["psf_edge"] == {"scale": 0.95}
    said = [n for n in second.notes if n.startswith("self-calibration")]  # told apart from the first fit's
    assert said and said[0].startswith("self-calibration (gains) through the PSF with its lost edge fitted (shrunk x0.9500)")
    assert not isinstance(make_stfm(matched, settings), EdgeRefit)
    assert not isinstance(make_stfm(wrong, replace(settings, psf_edge=False)), EdgeRefit)
