"""pnp coarse to fine (rngcam.recon.methods.pnp.make_pnp through rngcam.recon.methods.coarse_to_fine.CoarseToFine)."""

import math

import numpy as np
import pytest
import torch

from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.coarse_to_fine import CoarseToFine
from rngcam.recon.methods.pnp import PnP, PnPSettings, fine_level_settings, make_pnp
from tests.test_pnp import _problem, _psnr


def test_small_grids_stay_single_level_and_identical():
    p = _problem(size=32)
    settings = PnPSettings(schedule_iters=4, init="blend")
    made, plain = make_pnp(p, settings), PnP(p, settings)
    assert isinstance(made, PnP)
    for _ in range(2):
        made.step(), plain.step()
    torch.testing.assert_close(made.estimate(), plain.estimate(), rtol=0, atol=0)


def test_coarse_to_fine_reaches_the_full_grid_and_improves_on_its_start():
    p = _problem(size=32)
    stages = []
    m = make_pnp(p, PnPSettings(schedule_iters=6, init="blend"), stage=stages.append, factors=(2, 1))
    assert isinstance(m, CoarseToFine) and not m.final
    start = _psnr(m.estimate(), p.truth)
    result = run(m, LoopSettings(time_budget_s=None, max_iters=30, progress=False))
    assert m.final and m.estimate().shape == p.shape and result.status == "ok"
    assert m.steps == result.iterations and m.level_steps < m.steps  # counted over both levels
    assert any("level 2 of 2" in s for s in stages)
    assert m.method.init_source == "coarser level"
    assert m.method.s.sigma_start == pytest.approx(math.sqrt(0.05 * 0.01)) and m.method.s.schedule_iters == 3
    end = _psnr(m.estimate(), p.truth)
    assert np.isfinite(end) and end > start


def test_finer_level_norm_is_warm_started_and_matches_the_cold_norm():
    p = _problem(size=32)
    settings = PnPSettings(schedule_iters=2, init="blend")
    m = make_pnp(p, settings, factors=(2, 1))
    while not m.final:
        m.step()
    assert m.method.rs_norm_vector is None  # the full grid keeps no vector: no finer level needs it
    cold = p.rs_op().norm(iters=200, tol=1e-10, dtype=torch.float64)
    assert m.method.rs_norm_sq == pytest.approx(1.02 * cold ** 2, rel=0.03)


def test_fine_level_settings_take_up_the_schedule_half_way():
    s = fine_level_settings(PnPSettings(sigma_start=0.08, sigma_end=0.02, schedule_iters=9))
    assert s.sigma_start == pytest.approx(0.04) and s.sigma_end == 0.02 and s.schedule_iters == 4
    assert fine_level_settings(PnPSettings(schedule_iters=1)).schedule_iters == 1


def test_key_frame_detail_is_what_the_coarse_grid_cannot_hold():
    from rngcam.recon.methods.coarse_to_fine import bin_video
    from rngcam.recon.methods.pnp import with_key_frame_detail

    p = _problem(size=32)
    coarse_shape = (3, -(-p.shape[1] // 2), 16, 16)
    x0 = torch.full(p.shape, 0.5)
    out = with_key_frame_detail(p, x0, coarse_shape)
    assert out.shape == p.shape and bool((out >= 0).all())
    # it adds detail only: what it adds is mostly gone when binned back to the coarse grid
    added = out - x0
    assert float(added.abs().max()) > 0.05
    # (a video constant in 2x2x2 blocks keeps 0.35 of its norm when binned; this detail 0.16)
    assert float(bin_video(added, coarse_shape, 2).norm()) < 0.25 * float(added.norm())
    no_gs = type(p)(**{**p.__dict__, "b_gs": None})
    assert with_key_frame_detail(no_gs, x0, coarse_shape) is x0


def test_a_run_ended_on_a_coarse_level_keeps_the_key_frame_detail():
    from rngcam.recon.methods.coarse_to_fine import upsample
    from rngcam.recon.methods.pnp import key_frame_detail

    p = _problem(size=32)
    m = make_pnp(p, PnPSettings(schedule_iters=2, init="blend"), factors=(2, 1))
    m.step()
    coarse = m.method.estimate()
    plain = upsample(coarse, p.shape, 2)
    expect = (plain + key_frame_detail(p, tuple(coarse.shape))).clamp_min(0)
    torch.testing.assert_close(m.estimate(), expect)
    assert float((m.estimate() - plain).abs().max()) > 0.05  # (its gain is measured on smoke: bench/large_grids.md)
