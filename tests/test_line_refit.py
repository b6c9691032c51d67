"""The line-time refit: a second whole fit held at the line time the first learned far off, kept
where it explains the RS image better; said against the recorded line time; bounded; resumable."""

from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
from test_psf_edge import _Fit as _EdgeFit
from test_psf_edge import _through_checkpoint
from test_stfm_line_time import _moving_capture

from rngcam.errors import RngcamError
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.line_refit import LineRefit

RECORDED = 1e-4


class _Fit(_EdgeFit):
    """The PSF-edge tests' stand-in for a whole fit (stops after one step at RS residual `rs`), with a
    learned line-time factor `factor`."""

    def __init__(self, rs, factor):
        super().__init__(rs, None)
        self.factor, self.notes = factor, [f"RS line time learned with the fields: x{factor}"]

    def line_factor(self):
        return self.factor

    def line_time_report(self):
        return {"factor": self.factor, "recorded_s": RECORDED, "learned_s": RECORDED * self.factor}

    def resolved_settings(self):
        return {"line_time": self.line_time_report()}


def _refit(first_factor, first_rs, second_rs):
    made = []

    def another(factor, report):
        made.append((factor, report))
        fit = _Fit(second_rs, None)  # held at `factor`: it learns none
        fit.notes = ["a note"]  # held: learn_line_time off, so no line-time note of its own
        fit.line_time_report = lambda: None
        fit.resolved_settings = lambda: {"psf_edge": False, "line_refit": False}  # as the later fit was made
        return fit

    problem = SimpleNamespace(rs_timing=SimpleNamespace(line_time_s=RECORDED))
    return LineRefit(_Fit(first_rs, first_factor), problem, another, {"psf_edge": True}), made


def _run(method, limit=10):
    for _ in range(limit):
        method.step()
        if method.converged():
            return


@pytest.mark.parametrize("second_rs, kept", [(0.013, 1), (0.015, 0)])
def test_a_line_time_learned_far_off_starts_a_second_fit_there(second_rs, kept):
    method, made = _refit(1.014, 0.0143, second_rs)
    method.step()
    assert method.converged() is None and [m[0] for m in made] == [1.014]
    _run(method)
    assert method.report["kept"] == kept and len(made) == 1 and method.report["why"] == "one fit at the learned line time made"
    assert method.residuals()["rs"] == min(second_rs, 0.0143)
    line_time = method.resolved_settings()["line_time"]
    assert line_time["factor"] == pytest.approx(1.014)  # learned by the first fit, held by the second
    if kept:  # the misfit verdict reads the factor the kept fit ran at, against the recorded line time
        assert line_time["held"] and line_time["learned_s"] == pytest.approx(RECORDED * 1.014)
        assert method.notes[:2] == ["a note", "RS line time held at 101.4000 us per sensor row (x1.0140 the recorded "
                                    "100.0000 us), as the first fit learned it; the recorded line time looks off "
                                    "(the fit corrects part of a large error): measure it with `rngcam calibrate "
                                    "linetime --flicker`"]
    assert method.notes[-1].startswith("line time: a second fit held at the first fit's learned x1.0140")
    assert f"the {['first', 'second'][kept]} fit kept" in method.notes[-1]
    assert method.resolved_settings()["line_refits"]["kept"] == kept
    assert method.resolved_settings()["line_refit"] is True


@pytest.mark.parametrize("factor, why", [(1.006, "within 0.7 %"), (None, "did not learn the line time")])
def test_no_second_fit_where_the_line_time_is_near_the_recorded_one_or_not_learned(factor, why):
    method, made = _refit(factor, 0.0143, 0.001)
    _run(method)
    assert made == [] and method.report["kept"] == 0 and why in method.report["why"]
    assert not any(n.startswith("line time: a second fit") for n in method.notes)


def test_a_run_resumed_in_the_second_fit_makes_it_again_and_a_tampered_factor_is_refused(tmp_path):
    method, made = _refit(1.014, 0.0143, 0.013)
    method.step()
    method.converged()
    state = _through_checkpoint(method, tmp_path)
    again, made_again = _refit(1.014, 0.0143, 0.013)
    again.load_state_dict(state)
    assert [m[0] for m in made_again] == [1.014]
    _run(again)
    assert again.report["kept"] == 1
    for bad in ({"line_made": {1: 5.0}}, {"line_made": {1: float("nan")}}, {"line_current": 3}):
        with pytest.raises(RngcamError, match="line-time refit stage is not as rngcam writes it"):
            _refit(1.014, 0.0143, 0.013)[0].load_state_dict({**state, **bad})


@pytest.fixture(scope="module")
def slow_readout():
    return _moving_capture(0.97).to(torch.float32)


def test_make_stfm_wraps_where_the_line_time_is_learned_and_the_second_fit_holds_the_stretched_timing(slow_readout):
    def built(**kw):
        return make_stfm(slow_readout, STFMSettings(**{"preset": "fast", "dynamic_base": "none", "seed": 0,
                                                       "learn_line_time": "on", **kw}))

    method = built()
    assert isinstance(method, LineRefit)
    assert not isinstance(built(learn_line_time="off"), LineRefit)
    assert not isinstance(built(line_refit=False), LineRefit)
    assert not isinstance(built(learn_line_time="auto"), LineRefit)  # auto learns it with prior only
    assert not isinstance(make_stfm(replace(slow_readout, rs_timing=None),
                                    STFMSettings(preset="fast", dynamic_base="none", learn_line_time="on")), LineRefit)
    second = method._make_refit(0.98, dict(method.report))
    assert not isinstance(second, LineRefit) and second.line_factor() is None  # held there; never a third
    p = second.problem
    assert p.rs_timing.line_time_s == pytest.approx(0.98 * slow_readout.rs_timing.line_time_s)
    torch.testing.assert_close(p.rs_weights, slow_readout.rs_weights_at(0.98).to(p.rs_weights))


def test_the_stages_settings_and_their_reports_land_apart_in_metrics():
    from rngcam.recon.result import split_results

    method, _ = _refit(1.014, 0.0143, 0.013)
    _run(method)
    settings, results = split_results(method.resolved_settings())  # the kept second fit's, with the run's stages
    assert settings["line_refit"] is True and settings["psf_edge"] is True
    assert results["line_refits"]["kept"] == 1 and "line_refit" not in results and "psf_edge" not in results
