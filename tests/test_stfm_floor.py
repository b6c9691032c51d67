"""The default STFM: preset auto, the GS-only start as the floor of the output, a budget that
ends an unconverged fit says so."""

import numpy as np
import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon import registry
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.floor import StartFloor
from rngcam.recon.methods.stfm.recipe import make_stfm


class _Fixed(MethodBase):
    name = "fixed"
    stops_itself = True

    def __init__(self, video):
        self.video, self.notes = video, ["inner note"]

    def estimate(self):
        return self.video

    def budget_cut(self):
        return "inner cut"


def test_a_fit_worse_than_the_start_gives_the_start():
    p = tiny_sineball_problem(16).to(torch.float32)
    guard = StartFloor(_Fixed(torch.zeros(p.shape)), p)
    assert guard.start_name in ("blend", "interp") and np.isfinite(guard.start_rs)
    out = guard.estimate()
    assert torch.equal(out, guard.start_video) and out.abs().sum() > 0
    assert guard.notes[0] == "inner note" and "not below the best GS-only video" in guard.notes[-1]
    assert guard.resolved_settings()["start_floor"]["output_is_start"] is True
    # Everything else is the method's.
    assert guard.name == "fixed" and guard.stops_itself and guard.budget_cut() == "inner cut"


def test_a_fit_better_than_the_start_is_kept():
    p = tiny_sineball_problem(16).to(torch.float32)
    guard = StartFloor(_Fixed(p.truth.clone()), p)
    assert torch.equal(guard.estimate(), p.truth) and guard.notes == ["inner note"]
    assert guard.resolved_settings()["start_floor"]["output_is_start"] is False


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
