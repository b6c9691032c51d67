"""What an STFM fit learns about the rig is one kind of object (stfm/learned.py): each quantity is one
optimiser group of its own on its own schedule, a fit started from another takes its value without a
hold, and what it reports counts from where it started."""
import pytest
import torch
from test_stfm_line_time import _moving_capture

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.learned import Gains, Learned, Pose
from rngcam.recon.methods.stfm.line_time import LineTime
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.stage_configs import FitConfig, fit_config


@pytest.fixture(scope="module")
def capture():
    return _moving_capture(1.0, size=16).to(torch.float32)


def _fit(problem, **overrides):
    settings = STFMSettings(**{"preset": "prior", "dynamic_base": "none", "seed": 0, "learn_line_time": "on",
                               "learn_geometry": "shift", "fits": 1, **overrides})
    return STFM(problem, settings)


def _group(fit, learned: Learned) -> list[dict]:
    return [g for g in fit.optimiser.param_groups if any(q is learned.parameter for q in g["params"])]


def test_each_learned_quantity_is_one_group_on_its_own_schedule(capture):
    fit = _fit(capture)
    quantities = (fit.learned_gains, fit.learned_pose, fit.learned_line_time)
    assert [type(q) for q in quantities] == [Gains, Pose, LineTime] and all(isinstance(q, Learned) for q in quantities)
    config = fit.fit_config
    for q in quantities:
        assert q.learned and len(_group(fit, q)) == 1 and _group(fit, q)[0]["params"] == [q.parameter]
    # the pose and (this fit's motion starts from the search) the line time are held while the fields settle
    assert _group(fit, fit.learned_pose)[0]["hold_steps"] == config.pose_hold_steps
    assert _group(fit, fit.learned_pose)[0]["lr_ratio"] == pytest.approx(config.pose_lr_ratio * config.pose_lr_after_hold)
    assert fit.search_started() and _group(fit, fit.learned_line_time)[0]["hold_steps"] == config.line_hold_steps_search
    before = fit.learned_pose.parameter.detach().clone()
    for _ in range(3):
        fit.step()
    assert torch.equal(fit.learned_pose.parameter.detach(), before)  # held: no step reached it
    assert fit.pose() is not None and fit.line_factor() == pytest.approx(1.0)


def test_a_quantity_not_learned_has_no_group_and_reports_nothing(capture):
    fit = _fit(capture, learn_geometry="off", learn_line_time="off")
    assert not fit.learned_pose.learned and not _group(fit, fit.learned_pose) and fit.pose() is None
    assert not fit.learned_line_time.learned and fit.line_factor() is None and fit.line_time_report() is None
    assert fit.learned_geometry() is None
    one_camera = _fit(capture, no_gs=True)  # gains pin nothing without both cameras
    assert not one_camera.learned_gains.learned and not _group(one_camera, one_camera.learned_gains)


def test_a_fit_started_from_another_takes_its_values_without_a_hold(capture):
    first = _fit(capture)
    with torch.no_grad():
        first.learned_pose.parameter[:2] = torch.tensor([0.01, -0.02])
        first.learned_line_time.parameter.fill_(0.3)
    later = _fit(capture)
    later.start_pose(first.pose())
    later.start_line_factor(first.line_factor())
    assert later.learned_pose.inherited and later.learned_line_time.inherited
    assert _group(later, later.learned_pose)[0]["hold_steps"] == 0
    assert _group(later, later.learned_line_time)[0]["hold_steps"] == 0
    torch.testing.assert_close(later.pose(), first.pose())
    assert later.line_factor() == pytest.approx(first.line_factor(), rel=1e-6)
    finer = STFM(capture, first.settings, fields_from=first)  # a finer level: transfer, scaled to its grid
    assert finer.learned_pose.inherited
    torch.testing.assert_close(finer.learned_pose.parameter.detach(), first.learned_pose.parameter.detach())


def test_the_pose_applies_as_a_shift_both_ways(capture):
    pose = Pose(16, 16, "cpu")
    pose.enable("shift", True, FitConfig())
    with torch.no_grad():
        pose.parameter.copy_(torch.tensor([0.5, 0.0, 0.3, 0.1]))  # rotation and scale are held at zero
    assert pose.reading()[2:].abs().max() == 0
    yy, xx = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    frames = (0.5 + 0.4 * torch.sin(xx / 3) * torch.cos(yy / 4)).expand(3, 2, 16, 16)  # smooth: no aliasing
    there = pose.rs_view(frames)
    back, seen = pose.gs_view(there)
    assert seen is not None and seen.sum() > 0
    inner = (slice(None), slice(None), slice(2, -2), slice(2, -2))
    assert float((back - frames)[inner].detach().abs().max()) < 0.02  # there and back: the same image inside
    assert float((there - frames)[inner].detach().abs().max()) > 0.05  # moved


def test_the_fit_stage_numbers_of_the_start_and_the_decoding_are_checked():
    with pytest.raises(ConfigError, match="init_"):
        fit_config(STFMSettings(stages={"fit": {"init_lr": 0.0}}))
    with pytest.raises(ConfigError, match="canonical_knot_px"):
        fit_config(STFMSettings(stages={"fit": {"canonical_knot_px": 0.3}}))  # 1 / 0.3 is not whole
    assert fit_config(STFMSettings(stages={"fit": {"motion_knot_px": 4.0}})).motion_knot_px == 4.0
