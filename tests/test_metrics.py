"""Truth-based error measures."""

import math

import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon.metrics import error_visibility


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
