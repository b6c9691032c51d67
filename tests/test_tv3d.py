"""3-D TV (tv3d): FISTA without regularisation recovers the truth on a full-rank problem, the
objective never rises with restart, the fit improves on its start and hard anchoring holds."""

import itertools

import pytest
import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.tv3d import TV3D, TV3DSettings
from rngcam.recon.metrics import psnr
from rngcam.recon.problem import problem_from_video

DT = 1e-4


def _video(c=2, k=6, h=8, w=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand((c, k, h, w), generator=g, dtype=torch.float64)


def _psf(h=5, w=5, seed=1):
    p = torch.rand((1, h, w), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return p / p.sum()


def _full_rank_problem():
    """GS triggers that expose every frame alone make A_G the identity: full rank."""
    k, h = 6, 8
    rs = RollingShutterTiming(line_time_s=DT / 2, exposure_s=DT, rows=h, rows_per_bin=1)
    gs = GlobalShutterTiming(trigger_s=tuple(i * DT for i in range(k)), exposure_s=DT)
    return problem_from_video(_video(k=k, h=h), _psf(), rs, gs, dt_s=DT)


def _sineball_problem(size=12):
    return tiny_sineball_problem(size, psf_seed=1)


def _settings(**kw):
    return LoopSettings(**{"time_budget_s": None, "progress": False, **kw})



def test_fista_without_regularisation_recovers_truth_on_full_rank_problem():
    p = _full_rank_problem()
    m = TV3D(p, TV3DSettings(tau=0.0, init="zeros"))
    run(m, _settings(max_iters=300))
    assert psnr(m.estimate(), p.truth) > 60


@pytest.mark.parametrize("prox", ["haar", "exact"])
def test_objective_with_restart_never_increases(prox):
    p = _sineball_problem(8 if prox == "exact" else 12)
    m = TV3D(p.to(torch.float64), TV3DSettings(tau=5e-3, prox=prox, restart=True, init="zeros"))
    values = [m.state["F"]]
    for _ in range(15 if prox == "exact" else 40):
        values.append(m.step())
    assert all(b <= a * (1 + 1e-12) for a, b in itertools.pairwise(values))
    assert values[-1] < values[0]


def test_tv3d_improves_on_its_start():
    p = _sineball_problem()
    m = TV3D(p.to(torch.float32), TV3DSettings(tau=1e-3))
    start = psnr(m.estimate(), p.truth)
    run(m, _settings(max_iters=60))
    assert psnr(m.estimate(), p.truth) > start + 0.3


def test_hard_anchoring_reproduces_the_gs_frames():
    p = _sineball_problem()
    m = TV3D(p, TV3DSettings(gs_anchor="hard", tau=1e-3))
    run(m, _settings(max_iters=10))
    torch.testing.assert_close(p.gs_op().A(m.estimate()), p.b_gs, atol=1e-6, rtol=1e-6)
