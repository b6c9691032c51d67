"""Held-out measurement validation: the split, masked fitting without leakage, the score."""

import pytest
import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.errors import ConfigError
from rngcam.recon.holdout import HoldoutScorer, holdout_residuals
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.tv3d import TV3D, TV3DSettings, _Masked

DT = 1e-4


def _problem(size=12, seed=0):
    return tiny_sineball_problem(size, psf_seed=seed)


def _fit(problem, iters=15, **settings):
    m = TV3D(problem.to(torch.float64), TV3DSettings(**{"tau": 1e-3, **settings}))
    run(m, LoopSettings(time_budget_s=None, max_iters=iters, progress=False))
    return m.estimate()


def test_split_is_seeded_and_holds_out_the_asked_fraction():
    p = _problem(size=20)
    a, b, c = p.with_holdout(0.2, 0.1, seed=3), p.with_holdout(0.2, 0.1, seed=3), p.with_holdout(0.2, 0.1, seed=4)
    assert torch.equal(a.rs_train_rows, b.rs_train_rows) and torch.equal(a.gs_train_mask, b.gs_train_mask)
    assert not torch.equal(a.gs_train_mask, c.gs_train_mask)
    # RS rows go in blocks spanning one exposure (3 line times here): 0.2 * 20 rows -> one block of 3.
    assert p.rows_per_exposure() == 3
    held = torch.nonzero(~a.rs_train_rows).flatten().tolist()
    assert a.rs_train_rows.shape == (20,) and len(held) == 3 and held == list(range(held[0], held[0] + 3))
    single = p.with_holdout(0.2, 0.0, seed=3, rs_block=1)
    assert int((~single.rs_train_rows).sum()) == 4 and single.gs_train_mask is None
    spread = torch.nonzero(~p.with_holdout(0.5, 0.0, seed=0, rs_block=2).rs_train_rows).flatten()
    assert len(spread) == 10 and spread.min() < 5 and spread.max() >= 15  # strata cover all rows
    assert a.gs_train_mask.shape == (3, 20, 20) and int((~a.gs_train_mask).sum()) == 120
    assert p.rs_train_rows is None and not p.has_holdout and a.has_holdout  # the original is untouched
    held = a.rs_fit_mask(heldout=True)
    assert held.shape == (1, 20, 1) and torch.equal(held + a.rs_fit_mask(), torch.ones_like(held))
    assert a.gs_fit_mask().shape == (1, 3, 20, 20)
    moved = a.to(torch.float32)
    assert moved.rs_train_rows.dtype == torch.bool and torch.equal(moved.gs_train_mask, a.gs_train_mask)


@pytest.mark.parametrize("fraction", [-0.1, 1.0, 1.5])
def test_bad_fraction_is_a_clear_error(fraction):
    with pytest.raises(ConfigError, match="fraction"):
        _problem().with_holdout(fraction, 0.1)


def test_masked_operator_is_consistent():
    p = _problem(size=10).with_holdout(0.3, 0.3, seed=1)
    g = torch.Generator().manual_seed(0)
    for op, mask in ((p.rs_op(), p.rs_fit_mask()), (p.gs_op(), p.gs_fit_mask())):
        masked = _Masked(op, mask)
        x = torch.randn(op.domain_shape, generator=g, dtype=torch.float64)
        y = torch.randn(op.A(x).shape, generator=g, dtype=torch.float64)
        lhs, rhs = float((masked.A(x) * y).sum()), float((x * masked.A_adjoint(y)).sum())
        assert lhs == pytest.approx(rhs, rel=1e-10)
        assert torch.all(masked.A(x)[(mask == 0).expand_as(y)] == 0)


@pytest.mark.parametrize("anchor", ["soft", "hard"])
def test_fit_never_sees_held_out_measurements(anchor):
    """Changing only held-out measurements leaves the fit unchanged (also the initialisation)."""
    p = _problem().with_holdout(0.25, 0.25, seed=2)
    q = p.with_holdout(0.25, 0.25, seed=2)
    q.b_rs = torch.where(p.rs_fit_mask(heldout=True).bool(), 5 * p.b_rs + 1, p.b_rs)
    q.b_gs = torch.where(p.gs_fit_mask(heldout=True).bool().expand_as(p.b_gs), 3 * p.b_gs + 1, p.b_gs)
    va, vb = _fit(p, gs_anchor=anchor), _fit(q, gs_anchor=anchor)
    assert torch.allclose(va, vb, atol=1e-12)
    # ...while on the full problem the same change moves the fit.
    full_p, full_q = _problem(), _problem()
    full_q.b_rs, full_q.b_gs = q.b_rs, q.b_gs
    assert not torch.allclose(_fit(full_p, gs_anchor=anchor), _fit(full_q, gs_anchor=anchor), atol=1e-6)


def test_hard_anchor_holds_fitted_gs_pixels_only():
    p = _problem().with_holdout(0.2, 0.3, seed=5)
    m = TV3D(p.to(torch.float64), TV3DSettings(tau=1e-3, gs_anchor="hard"))
    run(m, LoopSettings(time_budget_s=None, max_iters=5, progress=False))
    pred = p.gs_op().A(m.estimate())
    fitted = p.gs_fit_mask().bool().expand_as(pred)
    # Projection then clamp at zero: fitted pixels match (the truth is positive, so no clamping).
    assert torch.allclose(pred[fitted], p.b_gs[fitted], atol=1e-8)
    assert not torch.allclose(pred[~fitted], p.b_gs[~fitted], atol=1e-3)


def test_score_is_the_relative_residual_on_held_out_measurements():
    p = _problem().with_holdout(0.25, 0.2, seed=0)
    assert holdout_residuals(p, p.truth) == {"heldout_rs": 0.0, "heldout_gs": 0.0, "heldout": 0.0}
    video = p.truth * 1.1
    s = holdout_residuals(p, video)
    # A uniform 10 % gain is a 10 % relative residual on any subset of the measurements.
    assert s["heldout_rs"] == pytest.approx(0.1) and s["heldout_gs"] == pytest.approx(0.1)
    assert s["heldout"] == pytest.approx(0.1)
    # Only held-out measurements count: damage confined to fitted RS rows' frames leaves heldout_rs.
    rows = p.rs_fit_mask(heldout=True)[0, :, 0].bool()
    b_rs = p.b_rs.clone()
    q = p.with_holdout(0.25, 0.2, seed=0)
    q.b_rs = torch.where(rows.view(1, -1, 1), b_rs, b_rs * 7)
    assert holdout_residuals(q, p.truth)["heldout_rs"] == 0.0
    with pytest.raises(ValueError, match="held-out split"):
        HoldoutScorer(_problem())


def test_score_of_a_diverged_video_is_infinite_not_nan():
    p = _problem().with_holdout(0.25, 0.2, seed=0)
    s = holdout_residuals(p, torch.full_like(p.truth, float("nan")))
    assert all(v == float("inf") for v in s.values())


def test_reconstruct_logs_the_held_out_score_next_to_the_training_residual(tmp_path):
    import csv
    import json

    from rngcam.evaluate.synthetic import CaptureSpec, make_bundle
    from rngcam.recon.runner import ReconSettings, reconstruct

    bundle = make_bundle(CaptureSpec(height=12, width=12), tmp_path / "b.h5")
    settings = ReconSettings(method="tv3d", time_budget_s=None, max_iters=4, progress=False, holdout=0.25)
    metrics = reconstruct(bundle, tmp_path / "out", settings, echo=lambda s: None)
    assert 0 < metrics["heldout_rs"] < 1 and "heldout_gs" not in metrics
    assert metrics["heldout"] == pytest.approx(metrics["heldout_rs"], rel=1e-12)  # RS rows only by default
    with open(tmp_path / "out" / "errors.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {"residual_rs", "residual_gs", "heldout", "heldout_rs"} <= set(rows[0])
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["heldout"] == metrics["heldout"]
    with pytest.raises(ConfigError, match="fitted methods"):
        ReconSettings(method="blend", holdout=0.1)
