"""Readout orders: exact exposure weights per order, adjoints, and the order through bundles and the CLI."""

import numpy as np
import pytest
import torch

from rngcam.physics.operators import PSFConvolution, inner, rolling_shutter_for
from rngcam.physics.timing import READOUTS, RollingShutterTiming, VideoGrid, check_readout


def _read_sequence(readout: str, n: int) -> dict[int, int]:
    """{sensor row: the line slot it is read in}, built by walking the readout as a sensor does."""
    if readout in ("top-down", "columns", "global-reset"):
        order = [[r] for r in range(n)]
    elif readout == "bottom-up":
        order = [[r] for r in reversed(range(n))]
    elif readout == "centre-out":  # two halves from the centre outwards, one row each per line
        upper, lower = list(range((n - 1) // 2 + (n % 2), -1, -1)), list(range(n // 2, n))
        if n % 2:  # the centre row alone, then a row of each half per line
            upper, lower = list(range(n // 2, -1, -1)), [None] + list(range(n // 2 + 1, n))
        order = [[r for r in pair if r is not None] for pair in zip(upper, lower, strict=False)]
    else:  # edges-in: the top and bottom rows first, then inwards
        order = [sorted({j, n - 1 - j}) for j in range((n + 1) // 2)]
    return {r: slot for slot, rows in enumerate(order) for r in rows}


def _brute_windows(t: RollingShutterTiming) -> tuple[np.ndarray, np.ndarray]:
    n = t.rows * t.rows_per_bin
    slot = _read_sequence(t.readout, n)
    assert sorted(slot) == list(range(n))
    lines = np.array([slot[r] for r in range(n)], dtype=np.float64)
    if t.readout == "global-reset":
        return np.full(n, t.trigger_s), t.trigger_s + t.exposure_s + lines * t.line_time_s
    starts = t.trigger_s + lines * t.line_time_s
    return starts, starts + t.exposure_s


def _brute_weights(t: RollingShutterTiming, grid: VideoGrid, samples: int = 20000) -> np.ndarray:
    """Midpoint-rule integral of each sensor row's exposure indicator over each frame, / dt, binned."""
    starts, ends = _brute_windows(t)
    times = (np.arange(grid.n_frames * samples) + 0.5) / samples * grid.dt_s
    inside = (times[None] >= starts[:, None]) & (times[None] < ends[:, None])
    per_row = inside.reshape(len(starts), grid.n_frames, samples).mean(axis=2)
    return per_row.reshape(t.rows, t.rows_per_bin, grid.n_frames).mean(axis=1)


@pytest.mark.parametrize("readout", READOUTS)
@pytest.mark.parametrize(("rows", "bin_", "dt_lines"), [(6, 1, 1.0), (5, 2, 1.7), (7, 1, 0.6)])
def test_weights_match_a_numeric_integral(readout, rows, bin_, dt_lines):
    line = 1e-5
    t = RollingShutterTiming(line, 2.37 * line, rows=rows, rows_per_bin=bin_, trigger_s=0.31 * line, readout=readout)
    grid = VideoGrid.covering(t, dt_s=dt_lines * line)
    w = t.weights(grid)
    np.testing.assert_allclose(w, _brute_weights(t, grid), atol=2e-4)
    starts, ends = _brute_windows(t)
    assert t.end_s == pytest.approx(ends.max(), rel=1e-12)
    assert grid.n_frames * grid.dt_s >= ends.max() > (grid.n_frames - 1) * grid.dt_s
    # every sensor row's weight is its exposure in frames
    np.testing.assert_allclose(w.sum(1), (ends - starts).reshape(rows, bin_).mean(1) / grid.dt_s, rtol=1e-12)


@pytest.mark.parametrize("readout", READOUTS)
def test_aligned_weights_are_exact_rects(readout):
    t = RollingShutterTiming(1e-5, 3e-5, rows=8, readout=readout)
    w = t.weights(VideoGrid.covering(t))
    starts, ends = _brute_windows(t)
    first, last = np.round(starts / 1e-5).astype(int), np.round(ends / 1e-5).astype(int)
    want = np.zeros_like(w)
    for r in range(8):
        want[r, first[r]:last[r]] = 1.0
    assert np.array_equal(w, want)


@pytest.mark.parametrize("readout", READOUTS)
def test_stretched_weights_follow_the_order_and_are_differentiable(readout):
    line = 1e-5
    t = RollingShutterTiming(line, 2.5 * line, rows=6, rows_per_bin=2, trigger_s=0.2 * line, readout=readout)
    grid = VideoGrid.covering(t, dt_s=1.3 * line)
    grid = VideoGrid(grid.dt_s, grid.n_frames + 3)  # room for a longer line time
    rows = torch.arange(6)
    one = t.stretched_weights(grid, rows, torch.tensor(1.0, dtype=torch.float64))
    np.testing.assert_allclose(one.numpy(), t.weights(grid), atol=1e-12)
    f = 1.07
    stretched = RollingShutterTiming(line * f, 2.5 * line, rows=6, rows_per_bin=2, trigger_s=0.2 * line,
                                     readout=readout)
    factor = torch.tensor(f, dtype=torch.float64, requires_grad=True)
    w = t.stretched_weights(grid, rows, factor)
    np.testing.assert_allclose(w.detach().numpy(), stretched.weights(grid), atol=1e-12)
    probe = torch.linspace(0, 1, grid.n_frames, dtype=torch.float64)
    (w * probe).sum().backward()
    eps = 1e-6
    hi = (t.stretched_weights(grid, rows, torch.tensor(f + eps, dtype=torch.float64)) * probe).sum()
    lo = (t.stretched_weights(grid, rows, torch.tensor(f - eps, dtype=torch.float64)) * probe).sum()
    assert float(factor.grad) == pytest.approx(float(hi - lo) / (2 * eps), rel=1e-5, abs=1e-9)
    if readout != "global-reset":  # a longer line time moves the later rows' exposure later
        assert float(factor.grad) != 0.0


def test_default_is_top_down_and_an_unknown_order_is_one_line():
    assert RollingShutterTiming(1e-5, 1e-5, rows=2).readout == "top-down"
    assert check_readout("edges-in") == "edges-in"
    with pytest.raises(ValueError) as err:
        RollingShutterTiming(1e-5, 1e-5, rows=2, readout="sideways")
    assert "\n" not in str(err.value) and "sideways" in str(err.value) and "centre-out" in str(err.value)


def _rand(shape, seed):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _rs_operator(readout, h=9, w=7, channels=2, bin_=1):
    """(operator on (C, K, H, W), its timing's weights, the PSF): rows along H, or W for columns."""
    rows = (w if readout == "columns" else h) // bin_
    t = RollingShutterTiming(1e-4, 2.6e-4, rows=rows, rows_per_bin=bin_, trigger_s=3e-5, readout=readout)
    weights = torch.from_numpy(t.weights(VideoGrid.covering(t, dt_s=0.7e-4)))
    psf = _rand((1, 5, 4), 1).abs()
    return rolling_shutter_for(psf, weights, (h, w), channels=channels, transposed=t.transposed), weights, psf


@pytest.mark.parametrize("readout", READOUTS)
def test_rs_adjoint_per_order(readout):
    op, _, _ = _rs_operator(readout)
    x = _rand(op.domain_shape, 2)
    y = _rand(op.A(x).shape, 3)
    lhs, rhs = float(inner(op.A(x), y)), float(inner(x, op.A_adjoint(y)))
    assert lhs == pytest.approx(rhs, rel=1e-12)
    xg = x.clone().requires_grad_(True)
    (vjp,) = torch.autograd.grad(inner(op.A(xg), y), xg)
    torch.testing.assert_close(op.A_adjoint(y), vjp, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("readout", READOUTS)
def test_rs_forward_per_order_is_the_explicit_weighted_sum(readout):
    """Each frame convolved, then row (or, along columns, column) r weighted by W[r, k], summed:
    exact also where a frame reaches two separate groups of rows (dual readouts)."""
    h, w = 9, 7
    op, weights, psf = _rs_operator(readout, h, w)
    v = _rand(op.domain_shape, 4)
    seen = PSFConvolution(psf, (h, w), batch_shape=(v.shape[1],), channels=2).A(v)  # (C, K, H, W)
    if readout == "columns":
        want = torch.einsum("ckhw,wk->chw", seen, weights)
    else:
        want = torch.einsum("ckhw,hk->chw", seen, weights)
    torch.testing.assert_close(op.A(v), want, rtol=1e-10, atol=1e-12)
