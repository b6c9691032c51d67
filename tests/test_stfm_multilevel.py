"""STFM coarse to fine (rngcam.recon.methods.stfm.multilevel): levels chosen, fields carried over, each
finer level starting where the coarser one ended, in the preset's own model."""

import numpy as np
import pytest
import torch

from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.coarse_to_fine import upsample
from rngcam.recon.methods.stfm import STFM, STFMSettings, make_stfm
from rngcam.recon.methods.stfm.fields import field_on_grid, make_field, transfer_fields
from rngcam.recon.methods.stfm.multilevel import make_multilevel, stfm_levels, stfm_time_factors
from rngcam.recon.metrics import video_metrics
from rngcam.sim.scenes import render_scene
from rngcam.sim.simulate import simulation_timing


def _toy_problem(h=32, w=48, scene="sineball"):
    from rngcam.recon.problem import problem_from_video
    from rngcam.sim.simulate import prepare_simulation_psf

    timing = simulation_timing((h, w))
    video = torch.from_numpy(render_scene(scene, timing.grid, (h, w), 0)).double()
    psf = prepare_simulation_psf(None, (h, w), (h, w), 0.25).grid
    return problem_from_video(video, torch.from_numpy(psf), timing.rs, timing.gs).to(torch.float32)


def _psnr(video, truth):
    return video_metrics(video.double(), truth.double(), np.arange(truth.shape[1]))["psnr_db"]


def test_levels_follow_the_grid_and_the_setting():
    p = _toy_problem()
    assert stfm_levels(p, STFMSettings()) == (1,)  # 32 px: one level
    big = type("P", (), {"shape": (3, 231, 228, 342), "gs_train_mask": None})()
    assert stfm_levels(big, STFMSettings()) == (4, 2, 1)
    assert stfm_levels(big, STFMSettings(coarse_to_fine=False)) == (1,)
    assert stfm_levels(p.with_holdout(0.1), STFMSettings(coarse_to_fine=True, preset="fast")) == \
        stfm_levels(p, STFMSettings(coarse_to_fine=True, preset="fast"))  # held-out RS rows reach every level
    big.gs_train_mask = torch.ones(228, 342, dtype=torch.bool)  # held-out GS pixels: one level
    assert stfm_levels(big, STFMSettings()) == (1,)


def test_transferred_plane_field_is_the_same_function_on_the_finer_grid():
    torch.manual_seed(0)
    coarse = make_field("planes", 3, 3, resolutions=(4, 8), time_resolutions=(3, 5), features=4, hidden=16)
    fine = make_field("planes", 3, 3, resolutions=(7, 15), time_resolutions=(5, 9), features=4, hidden=16)
    with torch.no_grad():  # give the planes some structure to carry over
        for q in coarse.planes:
            q.copy_(0.5 + 0.3 * torch.randn_like(q))
    transfer_fields(fine, coarse)
    axes = [torch.linspace(-1, 1, 20), torch.linspace(-1, 1, 13), torch.linspace(-1, 1, 6)]
    with torch.no_grad():
        a, b = field_on_grid(coarse, axes), field_on_grid(fine, axes)
    assert float((a - b).norm() / a.norm()) < 0.05  # bilinear planes resampled: nearly the same field
    other = make_field("planes", 3, 3, resolutions=(4,), features=4, hidden=16)
    with pytest.raises(ValueError):
        transfer_fields(other, coarse)


def test_prior_preset_fine_level_starts_from_the_coarse_model():
    p = _toy_problem()
    m = make_multilevel(p, STFMSettings(preset="prior"), "cpu", (2, 1), lambda q, s: make_stfm(q, s),
                        max_level_steps=30)
    coarse = m.method
    assert not m.final and coarse.resolved.dynamic_time is False
    for _ in range(30):
        m.step()
    assert m.final
    fine = m.method
    assert isinstance(fine, STFM) and fine.resolved.dynamic_time is False  # the prior's own model
    assert fine.resolved.lr == pytest.approx(0.25 * coarse.resolved.lr)
    # before any fine step the fine video is the coarse model on the finer grid
    up = upsample(coarse.estimate(), p.shape, m.time_factors[0])
    first = fine.estimate()
    assert float((first - up).norm() / up.norm()) < 0.1
    torch.testing.assert_close(fine.learned_gains.parameter, coarse.learned_gains.parameter)


def test_fast_preset_fine_level_fits_on_the_coarse_estimate_and_runs_to_the_end():
    p = _toy_problem()
    stages = []
    m = make_multilevel(p, STFMSettings(rows_per_step=4), "cpu", (2, 1), lambda q, s: make_stfm(q, s),
                        stage=stages.append, max_level_steps=20)
    start = _psnr(m.estimate(), p.truth)
    result = run(m, LoopSettings(time_budget_s=None, max_iters=60, progress=False))
    assert m.final and result.status == "ok" and any("level 2 of 2" in s for s in stages)
    fine = m.method
    assert fine.base.source == "given" and fine.resolved.dynamic_time is True
    assert fine.base.video.shape == p.shape
    video = m.estimate()
    assert video.shape == p.shape and torch.isfinite(video).all()
    assert _psnr(video, p.truth) > start - 0.5  # not worse than the GS-only start it came from
    levels = m.resolved_settings()["levels"]
    assert len(levels) == 2 and levels[0]["steps"] == 20
    comps = m.components()
    assert comps["motion"].shape == (2, *p.shape[1:])


def test_finer_level_rs_norm_is_warm_started_and_matches_a_converged_norm():
    p = _toy_problem()
    m = make_multilevel(p, STFMSettings(rows_per_step=4), "cpu", (2, 1), lambda q, s: make_stfm(q, s),
                        max_level_steps=3)
    while not m.final:
        m.step()
    fine = m.method
    assert isinstance(fine, STFM) and fine.rs_norm_vector is None  # the full grid keeps none
    converged = p.rs_op().norm(iters=300, tol=1e-12, dtype=torch.float64)
    assert fine.loss.rs_norm == pytest.approx(converged, rel=0.01) and fine.loss.rs_norm <= converged * (1 + 1e-5)


def test_rs_norm_start_is_used_and_its_last_iterate_kept():
    p = _toy_problem()
    s = STFMSettings(rows_per_step=4, dynamic_base="video", refine=False)
    cold = STFM(p, s)
    assert cold.rs_norm_vector is None  # no start given: no video-sized vector kept
    top = torch.ones(p.shape)  # near the top singular vector (the PSF is a low-pass filter)
    warm = STFM(p, s, rs_norm_start=top)
    assert warm.rs_norm_vector is not None and warm.rs_norm_vector.shape == p.shape
    assert warm.loss.rs_norm == pytest.approx(cold.loss.rs_norm, rel=0.01)
    worse = STFM(p, s, rs_norm_start=torch.randn(p.shape, generator=torch.Generator().manual_seed(1)))
    assert worse.loss.rs_norm < warm.loss.rs_norm  # six iterations from noise fall short: the start was used


def test_power_norm_from_a_zero_or_nan_start_is_the_operators_norm():
    import torch

    from rngcam.recon.methods.coarse_to_fine import power_norm

    class Diagonal:
        def A_normal(self, x):
            return x * torch.linspace(0.5, 4.0, x.numel(), dtype=x.dtype).reshape(x.shape)

    for start in (torch.zeros(2, 3, 4, 4), torch.full((2, 3, 4, 4), float("nan"))):
        norm, x = power_norm(Diagonal(), start.double(), iters=200, tol=1e-12)
        assert abs(norm - 2.0) < 1e-3 and torch.isfinite(x).all()


@pytest.mark.parametrize("preset", ["fast", "prior"])  # fast: a base video from the coarse estimate; prior: fields
def test_the_learned_gs_to_rs_shift_goes_to_the_finer_level_in_its_pixels(preset):
    from rngcam.recon.methods import selfcal

    p = _toy_problem()
    settings = STFMSettings(preset=preset, rows_per_step=4, learn_geometry="shift")
    m = make_multilevel(p, settings, "cpu", (2, 1), lambda q, s: make_stfm(q, s), max_level_steps=20)
    run(m, LoopSettings(time_budget_s=None, max_iters=10, progress=False))  # the coarse level only
    coarse = m.method
    assert getattr(coarse, "members", [coarse])[0].H == p.shape[2] // 2 and coarse.pose() is not None
    for fit in getattr(coarse, "members", [coarse]):  # a known shift at the coarse level, in its pixels
        fit.start_pose(torch.tensor([0.3, -0.2, 0.0, 0.0]))
    assert torch.allclose(coarse.pose(), torch.tensor([0.3, -0.2, 0.0, 0.0]), atol=1e-6)
    run(m, LoopSettings(time_budget_s=None, max_iters=11, progress=False))  # the coarse level's end, one fine step
    fine = m.method
    assert fine.H == p.shape[2] and fine.learned_pose.learned and fine.steps == 1
    np.testing.assert_allclose(fine.learned_geometry()["end"]["shift_px"], [0.6, -0.4], atol=0.05)  # 2x the pixels
    assert torch.isfinite(fine.estimate()).all()
    assert selfcal.describe(fine.learned_pose.matrix().detach().double().numpy())["scale"] == pytest.approx(1.0)


@pytest.mark.parametrize("preset", ["fast", "prior"])
def test_only_the_full_level_learns_the_line_time(preset):
    p = _toy_problem()
    settings = STFMSettings(preset=preset, rows_per_step=4, learn_line_time="on")
    m = make_multilevel(p, settings, "cpu", (2, 1), lambda q, s: make_stfm(q, s), max_level_steps=20)
    run(m, LoopSettings(time_budget_s=None, max_iters=10, progress=False))  # the coarse level only
    assert m.line_factor() is None  # a coarsened problem has no RS timing: the recorded line time
    run(m, LoopSettings(time_budget_s=None, max_iters=14, progress=False))  # the coarse level's end, 4 fine steps
    fine = m.method
    assert fine.H == p.shape[2] and m.line_factor() is not None and abs(m.line_factor() - 1) < 0.01
    assert torch.isfinite(fine.estimate()).all() and np.isfinite(m.residuals()["rs"])
    assert m.resolved_settings()["line_time"]["factor"] == pytest.approx(m.line_factor())


def test_a_coarse_level_under_a_budget_may_spend_its_share_of_what_is_left():
    from rngcam.recon.loop import Clock
    from rngcam.recon.methods.stfm.stage_configs import MultilevelConfig

    p = _toy_problem()  # 32 x 48: the fast preset's half-grid-first path
    clock = Clock(seconds=1000.0)
    m = make_multilevel(p, STFMSettings(rows_per_step=4), "cpu", (2, 1), lambda q, s: make_stfm(q, s),
                        clock=clock, max_level_steps=10_000)
    left = clock.left()
    assert m.level_share_s == pytest.approx(MultilevelConfig.half_grid_level_share * left, rel=0.05)
    m.level_step_s, m.level_steps = m.level_share_s, 10**6  # many cheap steps have used the share: the
    # next step moves on (the finer level fits in what is left)
    m.step()
    assert m.final


def test_the_half_grid_first_takes_most_of_a_budget():
    """Below 96 px the fast preset's full level is one short refinement: its half grid may spend
    `fit.half_grid_level_share` of a budget, not the larger grids' `fit.level_share` (which cut smoke's
    half grid under a budget longer than its own stop); the prior preset keeps CoarseToFine's; a stage
    setting changes the share."""
    from rngcam.recon.methods.coarse_to_fine import LEVEL_SHARE as DEFAULT_SHARE
    from rngcam.recon.methods.stfm.stage_configs import MultilevelConfig

    p = _toy_problem()
    fast = make_multilevel(p, STFMSettings(preset="fast"), "cpu", (2, 1), lambda q, s: make_stfm(q, s))
    prior = make_multilevel(p, STFMSettings(preset="prior"), "cpu", (2, 1), lambda q, s: make_stfm(q, s))
    config = MultilevelConfig()
    assert fast.time_factors == (1, 1) and fast.level_share == config.half_grid_level_share > config.level_share
    assert prior.time_factors == (2, 1) and prior.level_share == DEFAULT_SHARE
    set_share = STFMSettings(preset="fast", stages={"fit": {"half_grid_level_share": 0.6}})
    assert make_multilevel(p, set_share, "cpu", (2, 1), lambda q, s: make_stfm(q, s)).level_share == 0.6


def test_the_fast_preset_starts_on_the_half_grid_from_64_px():
    def shaped(h, w):
        return type("P", (), {"shape": (3, 67, h, w), "gs_train_mask": None})()

    assert stfm_levels(shaped(64, 64), STFMSettings(preset="fast")) == (2, 1)
    assert stfm_levels(shaped(64, 64), STFMSettings(preset="fast", coarse_to_fine=False)) == (1,)
    assert stfm_levels(shaped(64, 64), STFMSettings(preset="prior")) == (1,)  # carries its fields: one level
    assert stfm_levels(shaped(48, 64), STFMSettings(preset="fast")) == (1,)  # a 24 px half grid is too small
    # that half grid keeps every frame (binned in pairs, its fit learned a biased GS-to-RS shift); the
    # paper grid's levels bin frames as they bin pixels
    assert stfm_time_factors(shaped(64, 64), (2, 1)) == (1, 1)
    assert stfm_time_factors(shaped(228, 342), (4, 2, 1)) == (4, 2, 1)
    assert stfm_time_factors(shaped(64, 64), (2, 1), with_base=False) == (2, 1)  # prior: not measured


def test_a_coarse_level_keeps_the_finer_grids_gs_frames_up_to_a_size(monkeypatch):
    from rngcam.recon.methods import coarse_to_fine

    p = _toy_problem()
    q = coarse_to_fine.coarsen(p, 2)
    assert q.fine_gs.shape == p.gs_images().shape and torch.allclose(q.fine_gs, p.gs_images())
    assert coarse_to_fine.coarsen(q, 2).fine_gs is q.fine_gs  # always the finest grid's
    monkeypatch.setattr(coarse_to_fine, "FINE_GS_MAX_PIXELS", 32 * 48 - 1)
    assert coarse_to_fine.coarsen(p, 2).fine_gs is None


def test_a_coarse_levels_base_video_and_key_flows_come_from_the_finer_grid():
    from rngcam.recon.methods.baselines import interp, interp_warps
    from rngcam.recon.methods.coarse_to_fine import bin_space, coarsen

    p = _toy_problem()
    q = coarsen(p, 2)
    fine = p.gs_images().numpy()
    video = STFM(q, STFMSettings(preset="fast", dynamic_base="interp"), "cpu")
    expected = bin_space(torch.from_numpy(np.asarray(interp(fine, p.gs_times_s, q.frame_times_s), np.float32)), 16, 24)
    assert video.base.source == "interp" and torch.allclose(video.base.video, expected, atol=1e-5)
    keys = STFM(q, STFMSettings(preset="fast", dynamic_base="keys_interp"), "cpu")
    warps = interp_warps(fine, p.gs_times_s, q.frame_times_s)
    flows = torch.from_numpy(np.concatenate([warps.flow0, warps.flow1], axis=-1)) / torch.tensor([23.5, 15.5] * 2)
    assert keys.base.key_images.shape == (3, 3, 16, 24)  # the coarse grid's key frames, warped by the fine flows
    binned = bin_space(flows.permute(0, 3, 1, 2), 16, 24).permute(0, 2, 3, 1)  # coordinate units on both grids
    assert torch.allclose(keys.base.key_flow, binned, atol=1e-5) and float(binned.abs().max()) > 0


def test_the_full_levels_start_has_the_gs_only_videos_detail():
    from rngcam.recon.methods.coarse_to_fine import bin_video, coarsen
    from rngcam.recon.methods.stfm.multilevel import _with_detail

    p = _toy_problem(scene="smoke")
    for frames in (2, 1):  # a half grid that bins frames in pairs, or keeps them
        q = coarsen(p, 2, frames)
        coarse_truth = upsample(bin_video(p.truth, q.shape, frames), p.shape, frames)
        started = _with_detail(p, coarse_truth.clone(), q.shape)
        assert started.shape == p.shape and float(started.min()) >= 0
        gain = _psnr(started, p.truth) - _psnr(coarse_truth, p.truth)
        assert gain > 1, (frames, gain)  # the detail the half grid could not hold


def test_a_coarse_levels_key_warps_start_as_the_finer_grids_warps_binned():
    """Warped on the coarse grid, bilinear sampling blurs the binned key frames at each sub-pixel shift;
    the start is the warp made on the finer grid (where the flows are), binned; the fit's changes move it."""
    import torch.nn.functional as F

    from rngcam.recon.methods.baselines import interp_warps
    from rngcam.recon.methods.coarse_to_fine import bin_space, coarsen

    p = _toy_problem(scene="smoke")
    q = coarsen(p, 2)
    fine = p.gs_images()
    warps = interp_warps(fine.numpy(), p.gs_times_s, q.frame_times_s)
    order = np.argsort(p.gs_times_s, kind="stable")
    keys = fine[:, order].permute(1, 0, 2, 3)
    flows = torch.from_numpy(np.concatenate([warps.flow0, warps.flow1], axis=-1)) / torch.tensor([23.5, 15.5] * 2)
    gx, gy = torch.linspace(-1, 1, 48).view(1, 1, -1), torch.linspace(-1, 1, 32).view(1, -1, 1)
    left = torch.from_numpy(warps.left)

    def warped(images, f):
        grid = torch.stack([gx + f[..., 0], gy + f[..., 1]], dim=-1)
        return F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=True)

    w0 = torch.from_numpy(warps.weight0).clamp(1e-6, 1 - 1e-6)[:, None]
    expected = w0 * warped(keys[left], flows[..., :2]) + (1 - w0) * warped(keys[left + 1], flows[..., 2:])
    expected = bin_space(expected, 16, 24).permute(1, 0, 2, 3)

    fit = STFM(q, STFMSettings(preset="fast", dynamic_base="keys_interp"), "cpu")
    k = q.shape[1]
    u = torch.zeros(k, 16, 24, 4, requires_grad=True)
    start = fit.base.keys_at(u, torch.zeros(k, 16, 24), torch.arange(k))
    assert torch.allclose(start, expected.float(), atol=1e-5)
    coarse_only = fit.base.keys_at(u, torch.zeros(k, 16, 24), torch.arange(k)) - fit.base._start_offset.permute(1, 0, 2, 3)
    assert float((coarse_only - expected).abs().max()) > 1e-3  # the blur this removes is there on this scene
    start.sum().backward()
    assert float(u.grad.abs().sum()) > 0  # the flows' corrections still move the warps


@pytest.mark.parametrize("preset", ["fast", "prior"])
def test_a_coarse_level_wrapped_by_a_refit_stage_hands_its_fit_to_the_next(preset):
    """A refit stage wraps a level's fit where it applies (`--set fit.base=video` on a capture whose key rows
    find the PSF too large raised AttributeError at the level's end): the next level takes the wrapped fit."""
    from dataclasses import replace

    from rngcam.recon.methods.stfm.refits import Refits

    class Stage(Refits):  # a stage that wraps its fit and proposes nothing
        pass

    p = _toy_problem()
    one = STFMSettings(preset=preset, rows_per_step=4, dynamic_base="interp" if preset == "fast" else None)
    m = make_multilevel(p, one, "cpu", (2, 1),
                        lambda q, s: Stage(STFM(q, replace(s, fits=1)), q, lambda *a: None, {}), max_level_steps=5)
    run(m, LoopSettings(time_budget_s=None, max_iters=8, progress=False))
    assert m.final and isinstance(m.method, STFM) and torch.isfinite(m.estimate()).all()
