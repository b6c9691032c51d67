"""The default STFM: preset auto, the GS-only start as the floor of the output, a budget that
ends an unconverged fit says so."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon import registry
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods import rife as rife_method
from rngcam.recon.methods.baselines import interp
from rngcam.recon.methods.coarse_to_fine import coarsen
from rngcam.recon.methods.rife import RifeUnavailableError
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.floor import StartFloor, _paired_z
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.recipe import make_stfm, with_stage_settings


class _Fixed(MethodBase):
    name = "fixed"
    stops_itself = True

    def __init__(self, video):
        self.video, self.notes = video, ["inner note"]

    def estimate(self):
        return self.video

    def budget_cut(self):
        return "inner cut"


def _fake_rife(monkeypatch):
    """RIFE replaced by a weightless stand-in (the flow interpolation), as where the weights are missing
    the check makes do with the other two."""
    monkeypatch.setattr(rife_method, "rife", lambda *a, **k: (_ for _ in ()).throw(RifeUnavailableError("no weights")))


def test_without_a_split_a_fit_worse_than_the_start_gives_the_start(monkeypatch):
    _fake_rife(monkeypatch)
    p = tiny_sineball_problem(16).to(torch.float32)
    guard = StartFloor(_Fixed(torch.zeros(p.shape)), p)
    assert not guard.heldout and guard.start_name in ("blend", "interp") and np.isfinite(guard.start_rs)
    out = guard.estimate()
    assert torch.equal(out, guard.start_video) and out.abs().sum() > 0
    assert guard.notes[0] == "inner note" and guard.notes[-1].startswith("self-check: the fit explains the RS image")
    assert guard.notes[-1].endswith(f"the output is that video ({guard.start_name})")
    assert guard.resolved_settings()["start_floor"]["output_is_start"] is True
    # Everything else is the method's.
    assert guard.name == "fixed" and guard.stops_itself and guard.budget_cut() == "inner cut"


def test_a_fit_better_than_the_start_is_kept():
    p = tiny_sineball_problem(16).to(torch.float32)
    for problem in (p, p.with_holdout(0.2)):
        guard = StartFloor(_Fixed(problem.truth.clone()), problem)
        assert torch.equal(guard.estimate(), problem.truth) and guard.notes == ["inner note"]
        floor = guard.resolved_settings()["start_floor"]
        assert floor["output_is_start"] is False and floor["check"]["output"] == "fit" and "line" not in floor


def _noisy(problem, sigma: float, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    return replace(problem, b_rs=problem.b_rs + sigma * torch.randn(problem.b_rs.shape, generator=gen))


def test_on_held_out_rows_a_clearly_worse_fit_gives_way_and_says_so(monkeypatch):
    _fake_rife(monkeypatch)
    p = _noisy(tiny_sineball_problem(24).to(torch.float32), 0.002).with_holdout(0.2)
    guard = StartFloor(_Fixed(torch.zeros(p.shape)), p)
    assert guard.heldout
    out = guard.estimate()
    check = guard.resolved_settings()["start_floor"]["check"]
    assert set(check["parts"]) == {"held out", "fitted"} and check["output"] == guard.start_name
    assert all(part["z"] < -2 for part in check["parts"].values())
    assert torch.equal(out, guard.start_video)
    assert "the RS rows it did not fit and those it fitted" in guard.notes[-1]
    assert "held out rows" in guard.notes[-1] and "noise deviations" in guard.notes[-1]


def test_a_fit_worse_only_where_no_fitted_row_sees_is_kept(monkeypatch):
    """A held-out block is a stretch of time no fitted row sees, where a fit is at its weakest: a fit right
    on every frame a fitted row sees and blank in the gap is judged worse there than a video a little off
    everywhere, and better on the fitted rows; it is kept (a shaking camera's fit was given away so)."""
    p = _noisy(tiny_sineball_problem(24).to(torch.float32), 0.002).with_holdout(0.2)
    seen = p.rs_weights[p.rs_train_rows].sum(0) > 0
    assert not bool(seen.all())
    fit = p.truth.clone()
    fit[:, ~seen] = 0
    monkeypatch.setattr(rife_method, "rife", lambda *a, **k: (0.9 * p.truth).numpy())
    guard = StartFloor(_Fixed(fit), p, candidates=("rife",))
    guard.estimate()
    parts = guard.check["parts"]
    assert parts["held out"]["z"] < -2 and parts["fitted"]["z"] > 2 and guard.check["output"] == "fit"


def test_a_fit_as_good_as_the_reference_within_the_noise_is_kept(monkeypatch):
    """The truth plus an error against the reference (standing in for RIFE) as the truth less the same error:
    as good as each other, so the paired test's false alarms stay near its nominal rate (2.3 % at two
    deviations), where the held-out residuals alone pick whichever the noise favours."""
    p = tiny_sineball_problem(24).to(torch.float32)
    error = 0.02 * torch.randn(p.shape, generator=torch.Generator().manual_seed(7))
    monkeypatch.setattr(rife_method, "rife", lambda *a, **k: (p.truth - error).numpy())
    zs, lower = [], 0
    for seed in range(20):
        noisy = _noisy(p, 0.01, seed).with_holdout(0.2)
        guard = StartFloor(_Fixed(p.truth + error), noisy, candidates=("rife",))
        guard.estimate()
        held = guard.check["parts"]["held out"]
        zs.append((held["z"], guard.check["parts"]["fitted"]["z"]))
        lower += held["fit_residual"] < held["reference_residual"]
    alarms = sum(max(pair) < -2 for pair in zs)
    assert alarms <= 1 and sum(z < -2 for z, _ in zs) <= 2 and 4 <= lower <= 16, (zs, lower)
    # With no noise deviation allowed, the residuals alone decide: the fit gives way where both parts say worse.
    seed = int(np.argmin([max(pair) for pair in zs]))
    guard = StartFloor(_Fixed(p.truth + error), _noisy(p, 0.01, seed).with_holdout(0.2),
                       candidates=("rife",), significance=0.0)
    guard.estimate()
    assert guard.check["output"] == ("rife" if max(zs[seed]) < 0 else "fit")


def test_the_noise_estimate_sets_the_scale_of_the_test():
    assert _paired_z(0.0, 0.0) == 0.0 and _paired_z(1.0, 0.0) == float("inf") and _paired_z(-2.0, 1.0) == -2.0


def test_rife_is_a_candidate_where_it_runs(monkeypatch):
    p = tiny_sineball_problem(16).to(torch.float32)
    made = []

    def rife(keys, times, frames, **_k):
        made.append(True)
        return np.asarray(interp(keys, times, frames)) * 0 + float(p.truth.mean())  # a flat video: never best

    monkeypatch.setattr(rife_method, "rife", rife)
    guard = StartFloor(_Fixed(p.truth.clone()), p)
    assert made and guard.start_name in ("blend", "interp")
    guard = StartFloor(_Fixed(p.truth.clone()), p, candidates=("rife",))
    assert guard.start_name == "rife"


def test_on_a_cpu_a_large_grid_is_checked_without_rife_and_says_so(monkeypatch):
    """RIFE's video of the paper grid costs a CPU more than the fit's set-up: above RIFE_CPU_MAX_VOXELS the
    check's references are the other GS-only videos, with a note; on a GPU RIFE runs there, on that device."""
    from rngcam.recon.methods.stfm import floor

    p = tiny_sineball_problem(16).to(torch.float32)
    made = []

    def rife(keys, times, frames, device="cpu", **_k):
        made.append(device)
        return np.asarray(interp(keys, times, frames))

    monkeypatch.setattr(rife_method, "rife", rife)
    voxels = len(p.frame_times_s) * p.b_gs[0, 0].numel()
    monkeypatch.setattr(floor, "RIFE_CPU_MAX_VOXELS", voxels - 1)
    guard = StartFloor(_Fixed(p.truth.clone()), p)
    assert made == [] and guard.start_name in ("blend", "interp")
    assert any("self-check without RIFE's video" in n for n in guard.notes) and "inner note" in guard.notes
    on_gpu = _Fixed(p.truth.clone())
    on_gpu.device = "cuda:0"
    monkeypatch.setattr(rife_method, "rife", lambda keys, t, f, device="cpu", **k: made.append(device) or
                        np.asarray(interp(keys, t, f)))
    guard = StartFloor(on_gpu, p, candidates=("rife",))
    assert made == ["cuda:0"] and guard.start_name == "rife" and guard.left_note is None
    monkeypatch.setattr(floor, "RIFE_CPU_MAX_VOXELS", voxels)  # at the bound: RIFE stays, on the CPU
    made.clear()
    StartFloor(_Fixed(p.truth.clone()), p)
    assert made == ["cpu"]


def test_the_default_run_holds_rows_out_of_every_fit():
    p = _noisy(tiny_sineball_problem(32).to(torch.float32), 0.002)
    name, settings = registry.settings_for("stfm")
    m = make_stfm(p, settings, trace=True)
    held = [line for line in m.recipe if line.startswith("stage hold_out")]
    assert held and "RS rows held out" in held[0]
    assert "the held-out and the fitted RS rows" in next(line for line in m.recipe if line.startswith("stage start_floor"))
    fits = [m]
    while not isinstance(fits[-1], STFM) and hasattr(fits[-1], "_method"):
        fits.append(fits[-1]._method)
    floor = next(f for f in fits if isinstance(f, StartFloor))
    assert floor.heldout
    # Off, every row is fitted and the check reads them.
    off = make_stfm(p, with_stage_settings(settings, {"hold_out": {"fraction": 0}}), trace=True)
    assert any("left out: hold_out.fraction 0" in line for line in off.recipe)


def test_coarse_rows_bin_fitted_rows_only():
    p = tiny_sineball_problem(32).to(torch.float32).with_holdout(0.2)
    coarse = coarsen(p, 2)
    fine_held = ~p.rs_train_rows
    for i, fitted in enumerate(coarse.rs_train_rows.tolist()):
        assert fitted == (not bool(fine_held[2 * i: 2 * i + 2].any()))
    with pytest.raises(ValueError, match="held-out GS pixels"):
        coarsen(tiny_sineball_problem(16).to(torch.float32).with_holdout(0.1, 0.1), 2)


def test_the_default_stfm_is_auto_guarded_and_reports_self_calibration():
    p = tiny_sineball_problem(16).to(torch.float32)
    name, settings = registry.settings_for("stfm")
    assert settings.preset == "auto" and settings.start_floor and settings.self_calibrate == "gains"
    assert not STFMSettings().start_floor and STFMSettings().self_calibrate == "off"  # the bare model
    m = make_stfm(p, settings)
    assert isinstance(m, StartFloor)
    assert any(n.startswith("preset auto chose") for n in m.notes)
    for _ in range(3):
        m.step()
    rs = m.resolved_settings()
    assert rs["preset_choice"]["preset"] in ("prior", "fast") and "start_floor" in rs
    assert rs["self_calibration"]["mode"] == "gains"
    assert "not converged" in m.budget_cut() or "first convergence check" in m.budget_cut()
    # Off, nothing wraps the method.
    plain = make_stfm(p, STFMSettings(preset="fast", start_floor=False, self_calibrate="off", dynamic_base="interp"))
    assert not isinstance(plain, StartFloor) and not hasattr(plain.settings, "nothing")


def test_the_output_stays_in_the_range_light_and_the_sensor_allow():
    p = tiny_sineball_problem(16).to(torch.float32)
    wild = p.truth.clone()
    wild[:, 3, 2, 2], wild[:, 4, 5, 5] = 2.7, -0.4
    guard = StartFloor(_Fixed(wild), p)
    out = guard.estimate()
    assert float(out.max()) <= 1.0 and float(out.min()) >= 0.0
    assert torch.equal(out[:, 5:], p.truth[:, 5:])  # in range: untouched
    assert float(wild.max()) == pytest.approx(2.7)  # the fit's own video is not changed in place
