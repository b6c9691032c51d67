"""Subframes: the problem on frames `steps` x shorter weighs every exposure exactly there, in the
measurements' units, and measures a video that holds still within each frame as the output's grid
does; STFM fits the prior preset's runs on half-frames and shows their average, per frame, in its
estimate and components; where the timing is missing it fits the output's frames (or refuses, if asked)."""

import math
from dataclasses import replace

import pytest
import torch

from rngcam.errors import ConfigError
from rngcam.recon import ablation
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.settings import preset_settings
from rngcam.recon.methods.stfm.subframes import SubframesAveraged, subframes_averaged
from rngcam.recon.problem import build_problem


def _sineball(h=16, w=16):
    from rngcam.recon.problem import problem_from_video
    from rngcam.sim.scenes import render_scene
    from rngcam.sim.simulate import prepare_simulation_psf, simulation_timing

    timing = simulation_timing((h, w))
    video = torch.from_numpy(render_scene("sineball", timing.grid, (h, w), 0)).double()
    psf = prepare_simulation_psf(None, (h, w), (h, w), 0.25).grid
    return problem_from_video(video, torch.from_numpy(psf), timing.rs, timing.gs)


@pytest.mark.parametrize("steps", [2, 3])
def test_a_bundles_problem_on_shorter_frames_is_the_one_built_at_that_frame_time(shot, steps):
    from rngcam.formats.bundle_read import read_bundle

    bundle = read_bundle(shot)
    p = build_problem(bundle)
    q, direct = p.in_subframes(steps), build_problem(bundle, dt_s=p.grid.dt_s / steps)
    assert q.shape == (p.shape[0], p.shape[1] * steps, *p.shape[2:])
    n = direct.shape[1]  # that covers the exposures with up to steps - 1 frames fewer: none exposed
    assert p.shape[1] * steps - steps < n <= p.shape[1] * steps
    for name in ("rs_weights", "gs_weights"):
        w = getattr(q, name)
        assert torch.allclose(w[:, :n], getattr(direct, name), rtol=1e-9, atol=1e-12), name
        assert not w[:, n:].any()
    for name in ("b_rs", "b_gs"):  # the bundle's frames are float32 before they are scaled
        assert torch.allclose(getattr(q, name), getattr(direct, name), rtol=1e-6, atol=1e-9), name
    # each output frame's subframes together weigh what that frame weighs, in subframe units
    for w, w_sub in ((p.rs_weights, q.rs_weights), (p.gs_weights, q.gs_weights)):
        assert torch.allclose(w_sub.reshape(w.shape[0], -1, steps).sum(2), steps * w, atol=1e-9)
    assert torch.equal(q.truth[:, ::steps], p.truth) and p.in_subframes(1) is p


def test_a_video_still_within_each_frame_is_measured_alike_on_both_grids():
    p = _sineball()
    q = p.in_subframes(2)
    v = torch.rand(p.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    held = v.repeat_interleave(2, dim=1)
    assert torch.allclose(q.rs_op().A(held), 2 * p.rs_op().A(v), atol=1e-10)
    assert torch.allclose(q.gs_op().A(held), 2 * p.gs_op().A(v), atol=1e-10)
    assert torch.allclose(q.b_rs, 2 * p.b_rs) and torch.allclose(q.b_gs, 2 * p.b_gs)
    # ... and a video that moves within a frame is not: the rows see when in the frame it moved
    moving = held.clone()
    moving[:, 1::2] = moving[:, 1::2].roll(3, dims=-1)
    assert (q.rs_op().A(moving) - q.rs_op().A(subframes_averaged(moving, 2).repeat_interleave(2, 1))).abs().amax() > 1e-3


def test_an_ablated_camera_keeps_weights_of_the_right_shape():
    p = _sineball()
    no_gs = ablation.without(p, gs=True)
    q = no_gs.in_subframes(2)
    assert q.b_gs is None and q.gs_weights.shape == (0, 2 * p.shape[1]) and q.rs_weights.shape == (16, 2 * p.shape[1])


def test_a_problem_without_timing_cannot_be_subdivided():
    p = replace(_sineball(), rs_timing=None)
    assert not p.can_subdivide()
    with pytest.raises(ConfigError, match="timing"):
        p.in_subframes(2)


def test_the_prior_preset_fits_half_frames_and_shows_their_average():
    p = _sineball().to(torch.float32)
    method = make_stfm(p, STFMSettings(preset="prior", components="all"))
    assert isinstance(method, SubframesAveraged) and method.steps == 2
    assert method.problem.shape[1] == 2 * p.shape[1]  # the fit's own problem: half-frames
    for _ in range(3):
        method.step()
    inner = method._method.estimate()
    assert inner.shape[1] == 2 * p.shape[1]
    video = method.estimate()
    assert video.shape == p.shape
    assert torch.allclose(video, (inner[:, 0::2] + inner[:, 1::2]) / 2)
    parts = method.components()
    assert parts["alpha"].shape[1] == parts["motion"].shape[1] == p.shape[1]
    assert parts["static"].shape == (p.shape[0], *p.shape[2:])
    assert method.resolved_settings()["subframes"] == 2
    assert any(n.startswith(f"fitted on {2 * p.shape[1]} subframes, 2 to each") for n in method.notes)


def test_subframes_are_the_presets_and_can_be_set():
    p = _sineball().to(torch.float32)
    assert preset_settings("prior").subframes == 2 and preset_settings("fast").subframes == 1
    assert not isinstance(make_stfm(p, STFMSettings(preset="prior", subframes=1)), SubframesAveraged)
    assert not isinstance(make_stfm(p, STFMSettings(preset="fast")), SubframesAveraged)
    three = make_stfm(p, STFMSettings(preset="fast", subframes=3, dynamic_base="keys"))
    assert isinstance(three, SubframesAveraged) and three.steps == 3


def test_without_the_timing_a_run_fits_the_outputs_frames_unless_subframes_are_asked_for():
    p = replace(_sineball(), rs_timing=None).to(torch.float32)
    assert not isinstance(make_stfm(p, STFMSettings(preset="prior")), SubframesAveraged)
    with pytest.raises(ConfigError, match="subframes 2 needs the cameras' timing"):
        make_stfm(p, STFMSettings(preset="prior", subframes=2))


@pytest.mark.parametrize("bad", [0, 9, 1.5, "2"])
def test_subframes_out_of_range_are_refused_in_one_line(bad):
    with pytest.raises(ConfigError, match="subframes must be a whole number from 1 to 8"):
        STFMSettings(subframes=bad)


def test_a_track_is_drawn_through_the_subframes_instants():
    from rngcam.recon.methods.stfm.motion_search import through_subframes

    track = torch.tensor([[0.0, 0.0], [4.0, -2.0], [6.0, 2.0]])
    got = through_subframes(track, 2)
    want = torch.tensor([[0.0, 0.0], [1.0, -0.5],  # the first frame holds before its instant ...
                         [3.0, -1.5], [4.5, -1.0],  # ... the others a quarter frame towards each neighbour
                         [5.5, 1.0], [6.0, 2.0]])  # and the last holds after its own
    assert torch.allclose(got, want) and through_subframes(track, 1) is track
    assert torch.allclose(through_subframes(track, 4)[4:8].mean(0), track[1] + (track[2] - 2 * track[1] + track[0]) / 8)


def test_on_subframes_the_motion_search_and_the_line_time_count_in_the_outputs_frames():
    from rngcam.recon.methods.stfm.method import STFM
    from rngcam.recon.methods.stfm.motion_search import key_frame_layer, through_subframes, translation_track

    p = _sineball(32, 32).to(torch.float32)
    q = p.in_subframes(2)
    assert (q.subframes, q.in_subframes(2).subframes, q.to(torch.float64).subframes) == (2, 4, 2)
    from rngcam.recon.methods.coarse_to_fine import coarsen

    assert (coarsen(q, 2, 1).subframes, coarsen(q, 2, 2).subframes) == (2, 1)  # a coarser level's frames count too
    settings = STFMSettings(preset="prior", components="all", learn_line_time="on")
    one, two = STFM(p, settings), STFM(q, settings)
    assert two.learned_line_time.readout_frames == pytest.approx(one.learned_line_time.readout_frames)  # the factor learns at one rate in time
    tracks = []
    for fit in (one, two):
        keys = fit.problem.gs_images(gains=True).float()
        tracks.append(translation_track(fit, *key_frame_layer(keys, keys.shape[1] // 2)))
    assert tracks[1].shape == (2 * p.shape[1], 2)
    # the pass runs over the output's frames, charged what it is charged there: the same track, drawn
    # through the subframes' instants
    assert torch.allclose(tracks[1], through_subframes(tracks[0], 2))


def test_no_stop_test_ends_an_explained_search_started_fit_before_its_line_time_is_learned_and_its_step_has_decayed():
    from rngcam.recon.methods.stfm.method import STFM
    from rngcam.recon.methods.stfm.settings import EXPLAINED_RATIO
    from rngcam.recon.methods.stfm.stage_configs import FitConfig

    LINE_HOLD_STEPS_SEARCH, SEARCH_FIT_HALF_LIVES = FitConfig().line_hold_steps_search, FitConfig().search_fit_half_lives

    p = _sineball(32, 32).to(torch.float32)
    settings = STFMSettings(preset="prior", components="all", learn_line_time="on")
    fit = STFM(p, settings)
    every, window = fit.stop.check_every(), fit.stop.stall_window()
    assert fit.learned_line_time.schedule(fit.learned_pose.inherited)["hold_steps"] == LINE_HOLD_STEPS_SEARCH
    first = max(LINE_HOLD_STEPS_SEARCH + window, math.ceil(SEARCH_FIT_HALF_LIVES * fit.resolved.lr_half_life_steps))
    first = every * math.ceil(first / every)  # the first check from there
    assert first > LINE_HOLD_STEPS_SEARCH + window  # the step's decay, not the hold, sets it here
    fit.rs_noise_level = 1.0  # every residual is below it
    fit.steps = first - every
    assert fit.converged() is None
    fit.steps = first
    assert "reached the noise level" in fit.converged()
    residual = fit.residuals()["rs"]
    fit.rs_noise_level = residual / 1.1  # explained, not at the noise level: the stall test waits as well
    fit.stop.history = {first - every - window: 0.0}  # a residual that has not fallen at all
    fit.steps = first - every
    assert fit.converged() is None
    fit.stop.history, fit.steps = {first - window: 0.0}, first
    assert "fell less than" in fit.converged()
    fit.rs_noise_level = residual / (EXPLAINED_RATIO + 0.05)  # unexplained: stopped where it stalls, for the stages after
    fit.stop.history, fit.steps = {every: 0.0}, every + window
    assert fit.steps < first
    assert "fell less than" in fit.converged()
    plain = STFM(p, replace(settings, motion_init="flow"))  # motion not searched, nothing held: stopped at once
    plain.rs_noise_level, plain.steps = 1.0, plain.stop.check_every()
    assert "reached the noise level" in plain.converged()
