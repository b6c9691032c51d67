"""Grids of any shape (the lab's 228x342 aspect at toy sizes) and the RS operator's banded path."""

import numpy as np
import pytest
import torch

from rngcam.physics.operators import PSFConvolution, RollingShutter
from rngcam.physics.timing import RollingShutterTiming, VideoGrid
from rngcam.sim.scenes import render_scene
from rngcam.sim.simulate import SimulationError, grid_shape, simulate, simulation_timing


def _rs(h=12, w=18, rows_per_bin=2):
    t = RollingShutterTiming(line_time_s=1e-4 / rows_per_bin, exposure_s=3.1e-4, rows=h, rows_per_bin=rows_per_bin)
    grid = VideoGrid.covering(t, None)
    psf = torch.rand(3, 7, 9, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return RollingShutter(psf, torch.from_numpy(t.weights(grid)), width=w, channels=3)


def _dense_rs(op: RollingShutter, v: torch.Tensor) -> torch.Tensor:
    """The definition: convolve every frame, weight its rows, sum over frames."""
    return (op.conv.A(v) * op.weights.T[None, :, :, None]).sum(dim=1)


def test_banded_rs_equals_convolve_weight_sum_with_binned_rows():
    op = _rs()
    v = torch.randn(op.domain_shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(op.A(v), _dense_rs(op, v), rtol=1e-10, atol=1e-12)
    b = torch.randn(3, 12, 18, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    dense_adj = op.conv.A_adjoint(b[:, None] * op.weights.T[None, :, :, None])
    torch.testing.assert_close(op.A_adjoint(b), dense_adj, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("chunk", [1, 3, None])
def test_rs_results_do_not_depend_on_chunks_or_kept_buffers(chunk):
    op = _rs()
    gen = torch.Generator().manual_seed(3)
    v1, v2 = (torch.randn(op.domain_shape, dtype=torch.float64, generator=gen) for _ in range(2))
    first = op.A(v1, frame_chunk=chunk)
    op.A(v2, frame_chunk=chunk)  # reuses the buffers
    torch.testing.assert_close(op.A(v1, frame_chunk=chunk), first, rtol=0, atol=0)
    b = first.clone()
    a1 = op.A_adjoint(b, frame_chunk=chunk)
    assert a1.data_ptr() != op.A_adjoint(b, frame_chunk=chunk).data_ptr()  # results are never buffers
    torch.testing.assert_close(op.A_adjoint(b), a1, rtol=1e-12, atol=1e-12)


def test_rs_with_a_frame_no_row_sees():
    w = torch.zeros(6, 4, dtype=torch.float64)
    w[:, 1] = 1.0  # frames 0, 2, 3 reach no row
    op = RollingShutter(torch.ones(1, 3, 3, dtype=torch.float64) / 9, w, width=5, channels=1)
    v = torch.randn(1, 4, 6, 5, dtype=torch.float64)
    torch.testing.assert_close(op.A(v), PSFConvolution(op.conv.psf, (6, 5), channels=1).A(v[:, 1]))
    assert op.A_adjoint(torch.ones(1, 6, 5, dtype=torch.float64))[:, [0, 2, 3]].abs().max() == 0


def test_grid_shape_parses_and_rejects():
    assert grid_shape("228x342") == (228, 342)
    assert grid_shape(64) == (64, 64) and grid_shape("64") == (64, 64)
    for bad in ("228x", "4x342", "axb", 7, (8, 8, 8)):
        with pytest.raises(SimulationError):
            grid_shape(bad)


@pytest.mark.parametrize("scene", ["sineball", "smoke"])
def test_scenes_render_non_square(scene):
    grid = simulation_timing((16, 24)).grid
    video = render_scene(scene, grid, (16, 24), 0)
    assert video.shape == (3, grid.n_frames, 16, 24) and np.isfinite(video).all()
    assert video.std(axis=(0, 1)).mean() > 0  # not a flat image


def test_simulate_non_square_bundle_matches_the_grid(tmp_path):
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem

    b = simulate("sineball", tmp_path / "s.h5", size=(16, 24), noise=False)
    assert b.rs.frames.shape[1:3] == (16, 24) and b.truth.video.shape[-2:] == (16, 24)
    problem = build_problem(read_bundle(tmp_path / "s.h5"))
    assert problem.shape[-2:] == (16, 24) and problem.truth is not None
    # the bundle's RS image is the forward model of its truth (noise off, 12-bit quantisation)
    pred = problem.rs_op().A(problem.truth)
    assert float((pred - problem.b_rs).abs().max()) < 2e-3 * float(pred.abs().max())


def test_outputs_carry_the_time_axis(tmp_path):
    import json

    import av
    import tifffile

    from rngcam.recon import outputs

    video = np.random.default_rng(0).random((3, 5, 16, 24)).astype(np.float32)
    outputs.write_tiff(tmp_path / "v.tif", video, frame_interval_s=208e-6)
    with tifffile.TiffFile(tmp_path / "v.tif") as tif:
        assert tif.series[0].axes == "TCYX" and tif.imagej_metadata["finterval"] == pytest.approx(208e-6)
        np.testing.assert_array_equal(tif.asarray(), np.moveaxis(video, 0, 1))
    outputs.write_mp4(tmp_path / "p.mp4", video, capture_fps=1 / 208e-6)
    side = json.loads((tmp_path / "p.json").read_text())
    assert side["capture_fps"] == pytest.approx(4807.69, rel=1e-4) and side["slowdown"] == pytest.approx(160.26, rel=1e-3)
    with av.open(str(tmp_path / "p.mp4")) as f:
        assert "4,807.7 fps" in f.metadata.get("comment", "")


def _toy_problem(h=32, w=48):
    from rngcam.recon.problem import problem_from_video
    from rngcam.sim.simulate import prepare_simulation_psf

    timing = simulation_timing((h, w))
    video = torch.from_numpy(render_scene("sineball", timing.grid, (h, w), 0)).double()
    psf = prepare_simulation_psf(None, (h, w), (h, w), 0.25).grid
    return problem_from_video(video, torch.from_numpy(psf), timing.rs, timing.gs)


def test_coarse_problem_is_the_binned_fine_problem_for_a_video_constant_in_blocks():
    from rngcam.recon.methods.coarse_to_fine import block_matrix, coarsen

    p = _toy_problem()
    coarse = coarsen(p, 2)
    c, k2, h2, w2 = coarse.shape
    assert (h2, w2, k2) == (16, 24, -(-p.shape[1] // 2)) and coarse.grid.dt_s == 2 * p.grid.dt_s
    # A video constant over 2-frame blocks: the coarse GS model is exactly the GS model of the fine
    # video, binned; the RS model agrees up to the PSF's resampling.
    v2 = torch.rand(coarse.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    up = torch.einsum("jk,cjhw->ckhw", block_matrix(k2, p.shape[1], 2, torch.float64), v2)
    up = up.repeat_interleave(2, -2).repeat_interleave(2, -1)
    gs_fine = p.gs_op().A(up)
    gs_binned = gs_fine.reshape(*gs_fine.shape[:2], h2, 2, w2, 2).mean((3, 5))
    torch.testing.assert_close(coarse.gs_op().A(v2), gs_binned, rtol=1e-10, atol=1e-12)
    rs_fine = p.rs_op().A(up).reshape(c, h2, 2, w2, 2).mean((2, 4))
    rs_coarse = coarse.rs_op().A(v2)
    assert float((rs_coarse - rs_fine).norm() / rs_fine.norm()) < 0.05
    # the coarse truth is the binned truth and fits the coarse measurements about as well
    assert coarse.truth.shape == coarse.shape


def test_upsample_keeps_constants_and_linear_ramps_in_time():
    from rngcam.recon.methods.coarse_to_fine import upsample

    const = torch.full((3, 5, 6, 8), 0.25, dtype=torch.float64)
    torch.testing.assert_close(upsample(const, (3, 10, 12, 16), 2), torch.full((3, 10, 12, 16), 0.25,
                                                                               dtype=torch.float64))
    ramp = torch.arange(5, dtype=torch.float64)[None, :, None, None].expand(1, 5, 2, 2)
    fine = upsample(ramp, (1, 10, 2, 2), 2)[0, :, 0, 0]
    # fine frame k's centre is at coarse coordinate (k + 0.5) / 2 - 0.5 (clamped at the ends)
    expect = ((torch.arange(10, dtype=torch.float64) + 0.5) / 2 - 0.5).clamp(0, 4)
    torch.testing.assert_close(fine, expect)


def test_tv3d_coarse_to_fine_reaches_the_full_grid_and_improves_on_its_start():
    from rngcam.recon.loop import LoopSettings, run
    from rngcam.recon.methods.coarse_to_fine import CoarseToFine
    from rngcam.recon.methods.tv3d import TV3D, TV3DSettings
    from rngcam.recon.metrics import video_metrics

    p = _toy_problem().to(torch.float32)
    stages = []
    m = CoarseToFine(p, lambda q, x0: TV3D(q, TV3DSettings(), x0=x0), (2, 1), stage=stages.append,
                     max_level_steps=15)
    start = video_metrics(m.estimate().double(), p.truth.double(), np.arange(p.shape[1]))["psnr_db"]
    assert m.estimate().shape == p.shape and not m.final
    result = run(m, LoopSettings(time_budget_s=None, max_iters=40, progress=False))
    assert m.final and m.estimate().shape == p.shape and result.status == "ok"
    assert any("level 2 of 2" in s for s in stages)
    end = video_metrics(m.estimate().double(), p.truth.double(), np.arange(p.shape[1]))["psnr_db"]
    assert np.isfinite(end) and end > start


def test_coarse_levels_may_keep_every_frame():
    """time_factors (1, 1): the coarse level bins pixels only, its estimate reaches the full grid with
    every frame, and the next level's start is the coarse video with its frames as they were."""
    from rngcam.recon.methods.coarse_to_fine import CoarseToFine, upsample
    from rngcam.recon.methods.tv3d import TV3D, TV3DSettings

    p = _toy_problem().to(torch.float32)
    built, starts = [], []

    def make(q, x0):
        if x0 is not None:  # the coarse level's estimate as it ended, beside the start made of it
            starts.append((built[-1].estimate(), x0))
        built.append(TV3D(q, TV3DSettings(), x0=x0))
        return built[-1]

    m = CoarseToFine(p, make, (2, 1), max_level_steps=5, time_factors=(1, 1))
    c, k, h, w = p.shape
    assert m.problems[0].shape == (c, k, h // 2, w // 2)
    assert m.estimate().shape == p.shape
    for _ in range(6):
        m.step()
    assert m.final and len(starts) == 1
    coarse, start = starts[0]
    assert start.shape == p.shape
    # each fine frame is its own coarse frame, upsampled in space only (the start is kept in half precision)
    torch.testing.assert_close(start.float(), upsample(coarse.float(), p.shape, 1), rtol=1e-2, atol=1e-3)
    assert float((upsample(coarse.float(), p.shape, 2) - start.float()).abs().max()) > 1e-2
    with pytest.raises(ValueError, match="time factors"):
        CoarseToFine(p, make, (2, 1), time_factors=(2,))


def test_a_budget_that_ends_a_coarse_level_says_what_was_cut():
    from rngcam.recon.loop import LoopSettings, run
    from rngcam.recon.methods.coarse_to_fine import CoarseToFine
    from rngcam.recon.methods.tv3d import TV3D, TV3DSettings

    p = _toy_problem().to(torch.float32)
    m = CoarseToFine(p, lambda q, x0: TV3D(q, TV3DSettings(), x0=x0), (2, 1), max_level_steps=10 ** 6,
                     level_rtol=0.0)
    result = run(m, LoopSettings(time_budget_s=0.3, progress=False))
    assert any("level 1 of 2" in e and "not reached" in e for e in result.events)
    assert m.estimate().shape == p.shape


def test_power_norm_from_a_coarse_vector_matches_the_cold_norm():
    from rngcam.recon.methods.coarse_to_fine import coarsen, power_norm, upsample

    p = _toy_problem()
    coarse = coarsen(p, 2)
    _, vec = power_norm(coarse.rs_op(), torch.randn(coarse.shape, dtype=torch.float64,
                                                     generator=torch.Generator().manual_seed(0)))
    warm, _ = power_norm(p.rs_op(), upsample(vec, p.shape, p.shape[1] / coarse.shape[1]), iters=5)
    cold = p.rs_op().norm(iters=200, tol=1e-10)
    assert warm == pytest.approx(cold, rel=0.02) and warm <= cold * (1 + 1e-9)


def test_a_finer_level_that_cannot_fit_the_budget_is_not_started():
    from rngcam.recon.methods.coarse_to_fine import CoarseToFine
    from rngcam.recon.methods.tv3d import TV3D, TV3DSettings

    p = _toy_problem().to(torch.float32)
    stages = []
    from rngcam.recon.loop import Clock

    m = CoarseToFine(p, lambda q, x0: TV3D(q, TV3DSettings(), x0=x0), (2, 1), clock=Clock(seconds=1e-6),
                     stage=stages.append)
    for _ in range(3):
        m.step()
    assert not m.final and m.held_back and "too little budget left" in m.budget_cut()
    assert any("staying here" in s for s in stages) and m.estimate().shape == p.shape


def test_auto_budget_scales_with_the_problem_and_says_what_it_chose():
    from rngcam.recon.runner import auto_time_budget

    assert auto_time_budget("tv3d", (3, 67, 64, 64))[0] == pytest.approx(60.0)
    budget, why = auto_time_budget("tv3d", (3, 231, 228, 342))
    assert budget == pytest.approx(60 * (231 * 228 * 342 / (67 * 64 * 64)) ** 0.5) and f"{budget:.0f} s" in why
    assert auto_time_budget("stfm", (3, 231, 228, 342))[0] == 1800.0  # capped


def test_the_outputs_share_of_a_budget_grows_with_the_video_they_write():
    from rngcam.recon.settings import finish_seconds

    assert finish_seconds(60.0, (3, 67, 64, 64)) == pytest.approx(6.0)  # a tenth
    assert finish_seconds(300.0, (3, 231, 228, 342)) == pytest.approx(30.0)  # a tenth (outputs ~24 s)
    assert finish_seconds(3600.0, (3, 67, 64, 64)) == pytest.approx(60.0)  # at most a minute ...
    eight = finish_seconds(1200.0, (3, 459, 456, 684))  # ... unless the video takes longer to write
    assert 150.0 < eight < 250.0
    assert finish_seconds(100.0, (3, 459, 456, 684)) == pytest.approx(50.0)  # never more than half


def test_rs_rows_gradient_is_the_rows_adjoint():
    """STFM back-propagates through A_rows (the banded row DFT): autograd must give A_rows^T."""
    p = _toy_problem()
    op = p.rs_op()
    rows = torch.tensor([3, 4, 5, 6, 7])
    frames = torch.nonzero(op.weights[rows].sum(0) > 0).flatten()
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(3, len(frames), *p.shape[-2:], dtype=torch.float64, generator=gen).requires_grad_()
    y = torch.rand(3, len(rows), p.shape[-1], dtype=torch.float64, generator=gen)
    (op.A_rows(x, rows, frames) * y).sum().backward()
    torch.testing.assert_close(x.grad, op.A_rows_adjoint(y, rows, frames), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(op.A_rows(x.detach(), rows, frames), op.A(_scatter(x.detach(), frames, p.shape))[:, rows],
                               rtol=1e-10, atol=1e-12)


def _scatter(x, frames, shape):
    full = torch.zeros(shape, dtype=x.dtype)
    full[:, frames] = x
    return full
