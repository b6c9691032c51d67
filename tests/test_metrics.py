"""Truth-based error measures."""

import math

import numpy as np
import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon.metrics import (
    _dilate,
    dynamic_region,
    error_visibility,
    motion_metrics,
    object_metrics,
    one_object_scene,
    psnr_dynamic,
    ssim,
    video_metrics,
)


def _noisy(problem, level: float, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    problem.b_rs = problem.b_rs + level * torch.randn(problem.b_rs.shape, generator=g, dtype=problem.b_rs.dtype)
    problem.b_gs = problem.b_gs + level * torch.randn(problem.b_gs.shape, generator=g, dtype=problem.b_gs.dtype)
    return problem


def test_visibility_is_the_error_signal_over_the_noise_norm():
    p = _noisy(tiny_sineball_problem(), 0.01)
    error = 0.05 * torch.randn(p.truth.shape, generator=torch.Generator().manual_seed(1), dtype=p.truth.dtype)
    seen = error_visibility(p, p.truth + error)
    rs, gs = p.rs_op(), p.gs_op()
    assert math.isclose(seen["rs"], float(rs.A(error).norm() / (rs.A(p.truth) - p.b_rs).norm()), rel_tol=1e-9)
    assert math.isclose(seen["gs"], float(gs.A(error).norm() / (gs.A(p.truth) - p.b_gs).norm()), rel_tol=1e-9)
    assert error_visibility(p, p.truth) == {"rs": 0.0, "gs": 0.0}
    chunked = error_visibility(p, p.truth + error, frame_chunk=3)  # 14 frames: chunks of 3, 3, 3, 3, 2
    assert all(math.isclose(chunked[k], seen[k], rel_tol=1e-9) for k in seen)
    # Twice the error, twice as visible; a float32 estimate is measured the same.
    doubled = error_visibility(p, (p.truth + 2 * error).float())
    assert math.isclose(doubled["rs"], 2 * seen["rs"], rel_tol=1e-5)


def test_an_error_in_the_rs_null_space_is_invisible_to_the_rs_image_only():
    p = _noisy(tiny_sineball_problem(), 0.01)
    # Every RS row sums three consecutive frames: a period-3 flicker (+1, -1, 0) adds nothing to any row.
    flicker = torch.tensor([1.0, -1.0, 0.0], dtype=p.truth.dtype).repeat(p.truth.shape[1])[:p.truth.shape[1]]
    assert all(int((w > 0).sum()) == 3 and bool((w[w > 0] == 1).all()) for w in p.rs_weights)
    seen = error_visibility(p, p.truth + 0.1 * flicker[None, :, None, None])
    assert seen["rs"] < 1e-9
    assert seen["gs"] > 1


def test_visibility_without_noise_or_truth():
    p = tiny_sineball_problem()  # noiseless
    assert error_visibility(p, p.truth) == {"rs": 0.0, "gs": 0.0}
    assert error_visibility(p, p.truth + 0.1) == {"rs": math.inf, "gs": math.inf}
    p.truth = None
    assert all(math.isnan(v) for v in error_visibility(p, torch.zeros(3, 14, 12, 12)).values())


def _disc_video(centres, size=40, radius=3.0, background=0.2, value=0.9):
    """(3, K, size, size) a bright disc at each (x, y) centre over a constant background."""
    ys, xs = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                            indexing="ij")
    frames = []
    for cx, cy in centres:
        disc = ((xs - cx) ** 2 + (ys - cy) ** 2 <= radius ** 2).double()
        frames.append(background + (value - background) * disc)
    return torch.stack(frames)[None].expand(3, -1, -1, -1).clone()


CENTRES = [(11.0 + 3 * k, 20.0) for k in range(7)]  # a pixel is covered in < half the frames


def test_centroid_error_is_the_shift_of_the_object_and_ghost_is_zero_for_one_object():
    truth = _disc_video(CENTRES)
    shifted = _disc_video([(x + 2, y) for x, y in CENTRES])
    m = object_metrics(shifted, truth)
    assert abs(m["centroid_error_median_px"] - 2.0) < 1e-9 and abs(m["centroid_error_p90_px"] - 2.0) < 1e-9
    assert m["ghost_median"] == 0.0  # 2 px off: inside the true disc grown by 2 px: no signal outside it
    same = object_metrics(truth, truth)
    assert same["centroid_error_median_px"] == 0.0 and same["ghost_max"] == 0.0


def test_a_split_object_has_a_large_ghost_share_even_with_its_centroid_right():
    truth = _disc_video(CENTRES)
    # Half the disc's contrast on either side, 9 px away: the mean position is right, the picture is not.
    left = _disc_video([(x - 9, y) for x, y in CENTRES]) - 0.2
    right = _disc_video([(x + 9, y) for x, y in CENTRES]) - 0.2
    split = 0.2 + 0.5 * (left + right)
    m = object_metrics(split, truth, frames=np.arange(1, 6))
    assert m["centroid_error_median_px"] < 0.5
    assert m["ghost_median"] > 0.9


def test_dynamic_psnr_sees_only_the_moving_region():
    truth = _disc_video(CENTRES)
    region = dynamic_region(truth)
    assert region.shape == (7, 40, 40) and not bool(region[:, 0, 0].any())
    for k, (cx, cy) in enumerate(CENTRES):  # the disc (radius 3) grown by 2 px, in its own frame
        assert bool(region[k, int(cy), int(cx) - 5:int(cx) + 6].all()) and not bool(region[k, int(cy) - 7].any())
    corner_error = truth.clone()
    corner_error[:, :, 0:2, 0:2] += 0.3  # far from the disc's path: the whole-frame PSNR drops, the dynamic one not
    assert psnr_dynamic(corner_error, truth) == math.inf
    ball_error = truth + 0.1 * region[None].double()
    assert abs(psnr_dynamic(ball_error, truth) - 20.0) < 1e-9
    still = truth[:, :1].expand(-1, 7, -1, -1)
    assert math.isnan(psnr_dynamic(still, still))
    out = motion_metrics(ball_error, truth, np.arange(1, 6), one_object=True)
    assert set(out) == {"psnr_dynamic_db", "centroid_error_median_px", "centroid_error_p90_px", "ghost_median",
                        "ghost_max"}


def test_the_moving_region_is_grown_the_same_in_frame_chunks():
    gen = torch.Generator().manual_seed(0)
    mask = torch.rand(37, 20, 24, generator=gen) > 0.97  # more frames than one chunk, a part-filled last one
    whole = torch.nn.functional.max_pool2d(mask.float()[:, None], 5, stride=1, padding=2)[:, 0] > 0
    assert torch.equal(_dilate(mask, 2), whole) and torch.equal(_dilate(mask, 0), mask)


def test_one_object_scene_reads_the_simulated_rig():
    assert one_object_scene("name: sim\nmock:\n  scene: sineball\n  seed: 0\n")
    assert not one_object_scene("mock:\n  scene: smoke\n")
    assert not one_object_scene("")
    assert not one_object_scene("mock: [unbalanced")


def test_video_metrics_ssim_of_both_frame_sets_from_one_pass_matches_each_alone():
    """video_metrics filters once and averages per frame; the figures equal ssim() over each frame
    set, with and without a mask, and match a direct float64 SSIM of one frame."""
    gen = torch.Generator().manual_seed(0)
    truth = torch.rand(3, 9, 24, 30, generator=gen)
    est = (truth + 0.1 * torch.randn(truth.shape, generator=gen)).clamp(0, 1)
    inter = np.array([1, 2, 4, 7])
    mask = torch.ones(24, 30, dtype=torch.bool)
    mask[:, :12] = False
    for m in (None, mask):
        out = video_metrics(est, truth, inter, m)
        assert math.isclose(out["ssim"], ssim(est, truth, m), rel_tol=1e-6)
        assert math.isclose(out["ssim_intermediate"], ssim(est, truth, m, frames=inter), rel_tol=1e-6)
        assert out["ssim_intermediate"] != out["ssim"]
    # one frame, one channel, by hand: Gaussian 11x11 'valid' windows
    x, y = est[:1, :1].double(), truth[:1, :1].double()
    g = torch.exp(-((torch.arange(11.0) - 5) ** 2) / (2 * 1.5 ** 2)).double()
    k = (g[:, None] * g[None, :]) / g.sum() ** 2

    def blur(z):
        return torch.nn.functional.conv2d(z.reshape(1, 1, 24, 30), k[None, None])

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx ** 2, blur(y * y) - my ** 2, blur(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    direct = (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))).mean()
    assert math.isclose(ssim(est[:1, :1], truth[:1, :1]), float(direct), rel_tol=1e-5)


def test_metrics_json_is_strict_json_with_null_where_a_figure_is_not_a_number(tmp_path):
    import json

    import numpy as np
    import pytest

    from rngcam.recon.outputs import write_metrics

    metrics = {"error_visibility": {"rs": 3.1, "gs": math.nan}, "psnr_db": np.float32(24.5),
               "log": [{"objective": float("nan"), "wall_s": math.inf}], "steps": np.int64(3)}
    write_metrics(tmp_path / "metrics.json", metrics)
    text = (tmp_path / "metrics.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text, parse_constant=lambda name: pytest.fail(f"{name} in metrics.json"))
    assert back["error_visibility"] == {"rs": 3.1, "gs": None} and back["log"][0] == {"objective": None, "wall_s": None}
    assert back["psnr_db"] == pytest.approx(24.5) and back["steps"] == 3


def test_psnr_works_in_chunks_of_a_few_mb_and_equals_the_whole_array_formula():
    """A large grid's frames are scored a few at a time (each float64 temporary at most CHUNK_BYTES, at
    least one frame): the figure is the whole array's, over all frames and over a frame subset."""
    from rngcam.recon.metrics import CHUNK_BYTES, _frame_chunks, psnr

    gen = torch.Generator().manual_seed(1)
    truth = torch.rand(3, 20, 96, 128, generator=gen)  # 295 kB a frame in float64: 14 frames a chunk
    est = (truth + 0.05 * torch.randn(truth.shape, generator=gen)).clamp(0, 1)
    chunks = [e.shape[1] for e, _ in _frame_chunks(est, truth)]
    assert sum(chunks) == 20 and len(chunks) > 1
    assert max(chunks) * 8 * 3 * 96 * 128 <= CHUNK_BYTES
    frames = np.array([0, 3, 4, 19])
    for f in (None, frames):
        e, t = (est, truth) if f is None else (est[:, f], truth[:, f])
        whole = 10 * math.log10(1 / float(((e.double() - t.double()) ** 2).mean()))
        assert math.isclose(psnr(est, truth, frames=f), whole, rel_tol=1e-12)
    big = torch.zeros(3, 2, 700, 700)  # one frame over the budget: one frame a chunk
    assert [e.shape[1] for e, _ in _frame_chunks(big, big)] == [1, 1]


def test_gs_forward_in_chunks_is_the_operator():
    """The GS prediction the visibility and residuals use (float64, a few frames at a time) is the
    operator's weighted sum of frames, for any chunk."""
    from rngcam.recon.metrics import gs_forward

    problem = tiny_sineball_problem()
    gen = torch.Generator().manual_seed(2)
    video = torch.rand(problem.shape, generator=gen)
    op = problem.gs_op()
    expected = torch.einsum("ckhw,gk->cghw", video.double(), op.weights.double())
    for chunk in (None, 1, 3, 1000):
        got = gs_forward(op, video, chunk)
        assert got.dtype == torch.float64 and got.shape == expected.shape
        assert torch.allclose(got, expected, rtol=1e-12, atol=1e-12)
