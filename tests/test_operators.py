"""Every linear operator: adjointness in float64, A_adjoint == autograd VJP, correctness of A."""

import numpy as np
import pytest
import torch
from scipy.signal import convolve2d

from rngcam.physics.operators import (
    GlobalShutter,
    PSFConvolution,
    RollingShutter,
    Stacked,
    inner,
)
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.device)]


def _rand(shape, seed, dtype=torch.float64):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _rs_gs(h=9, w=7, channels=3, psf_shape=(5, 6), psf_channels=1):
    rs_t = RollingShutterTiming(line_time_s=1e-4, exposure_s=2.6e-4, rows=h, rows_per_bin=1)
    gs_t = GlobalShutterTiming(trigger_s=(0.0, 4e-4, 7.5e-4), exposure_s=2.6e-4)
    grid = VideoGrid.covering(rs_t, gs_t)
    psf = _rand((psf_channels, *psf_shape), 1).abs()
    rs = RollingShutter(psf, torch.from_numpy(rs_t.weights(grid)), width=w, channels=channels)
    gs = GlobalShutter(torch.from_numpy(gs_t.weights(grid)), channels, (h, w))
    return rs, gs


def _operators():
    rs, gs = _rs_gs()
    rs_colour, gs_colour = _rs_gs(h=8, w=10, psf_shape=(9, 4), psf_channels=3)
    return {
        "conv-mono-odd": PSFConvolution(_rand((1, 5, 3), 2), (7, 11), batch_shape=(2,), channels=3),
        "conv-colour": PSFConvolution(_rand((3, 6, 6), 3), (8, 8)),
        "conv-psf-larger-than-image": PSFConvolution(_rand((1, 13, 17), 4), (6, 5)),
        "rolling-shutter": rs,
        "rolling-shutter-colour-psf": rs_colour,
        "global-shutter": gs,
        "stacked": Stacked(rs, gs, psi=0.37),
        "stacked-psi0": Stacked(rs_colour, gs_colour, psi=0.0),
    }


def _domain(op):
    return op.domain_shape


OPS = _operators()


def _random_measurement(op, seed):
    y = op.A(_rand(_domain(op), 99))
    if isinstance(y, tuple):
        return tuple(_rand(t.shape, seed + i) for i, t in enumerate(y))
    return _rand(y.shape, seed)


@pytest.mark.parametrize("name", sorted(OPS))
def test_adjointness_float64(name):
    op = OPS[name]
    x = _rand(_domain(op), 10)
    y = _random_measurement(op, 20)
    lhs = float(inner(op.A(x), y))
    rhs = float(inner(x, op.A_adjoint(y)))
    assert abs(lhs - rhs) <= 1e-10 * max(abs(lhs), abs(rhs), 1e-30)


@pytest.mark.parametrize("name", sorted(OPS))
def test_adjoint_equals_autograd_vjp(name):
    op = OPS[name]
    x = _rand(_domain(op), 11).requires_grad_(True)
    y = _random_measurement(op, 21)
    (vjp,) = torch.autograd.grad(inner(op.A(x), y), x)
    torch.testing.assert_close(op.A_adjoint(y), vjp, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("chunk", [1, 2, 5, 100])
def test_rolling_shutter_in_frame_chunks_equals_all_frames_at_once(chunk):
    for name in ("rolling-shutter", "rolling-shutter-colour-psf"):
        op = OPS[name]
        x = _rand(_domain(op), 13)
        torch.testing.assert_close(op.A(x, frame_chunk=chunk), op.A(x), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", sorted(OPS))
@pytest.mark.parametrize("device", DEVICES)
def test_float32_matches_float64(name, device):
    op = OPS[name]
    x = _rand(_domain(op), 12)
    y64 = op.A(x.to(device))
    y32 = op.A(x.to(device, torch.float32))
    if not isinstance(y64, tuple):
        y64, y32 = (y64,), (y32,)
    for a, b in zip(y64, y32):
        assert b.dtype == torch.float32
        torch.testing.assert_close(b.double(), a, rtol=1e-4, atol=1e-4 * float(a.abs().max()))


@pytest.mark.parametrize("image,psf", [((7, 11), (5, 3)), ((8, 8), (6, 6)), ((6, 5), (13, 17)),
                                       ((1, 1), (3, 3)), ((4, 9), (1, 1))])
def test_linear_convolution_equals_direct(image, psf):
    x = _rand((1, *image), 30)
    h = _rand((1, *psf), 31)
    op = PSFConvolution(h, image)
    full = convolve2d(x[0].numpy(), h[0].numpy(), mode="full")
    oy, ox = psf[0] // 2, psf[1] // 2
    expected = full[oy:oy + image[0], ox:ox + image[1]]
    np.testing.assert_allclose(op.A(x)[0].numpy(), expected, rtol=1e-10, atol=1e-10)


def test_delta_psf_at_centre_is_identity():
    psf = torch.zeros(1, 5, 4, dtype=torch.float64)
    psf[0, 2, 2] = 1.0
    x = _rand((3, 2, 6, 7), 40)
    torch.testing.assert_close(PSFConvolution(psf, (6, 7)).A(x), x)


def test_rolling_shutter_matches_explicit_sum():
    rs, _ = _rs_gs()
    v = _rand(rs.domain_shape, 50)
    conv = rs.conv.A(v)
    expected = torch.zeros(v.shape[0], v.shape[2], v.shape[3], dtype=v.dtype)
    for i in range(v.shape[2]):
        for k in range(v.shape[1]):
            expected[:, i] += rs.weights[i, k] * conv[:, k, i]
    torch.testing.assert_close(rs.A(v), expected)


def test_static_scene_scales_by_exposure_over_dt():
    # A static scene: each GS frame sees v * exposure/dt (sum of its weights).
    _, gs = _rs_gs()
    frame = _rand(gs.domain_shape[:1] + gs.domain_shape[2:], 60)
    v = frame[:, None].expand(gs.domain_shape).contiguous()
    out = gs.A(v)
    for g in range(out.shape[1]):
        torch.testing.assert_close(out[:, g], frame * gs.weights[g].sum())


def _dense(op):
    n = int(np.prod(_domain(op)))
    cols = []
    for j in range(n):
        e = torch.zeros(n, dtype=torch.float64)
        e[j] = 1
        y = op.A(e.reshape(_domain(op)))
        y = torch.cat([t.ravel() for t in y]) if isinstance(y, tuple) else y.ravel()
        cols.append(y)
    return torch.stack(cols, dim=1).numpy()


@pytest.mark.parametrize("name", ["rolling-shutter", "global-shutter", "stacked"])
def test_power_iteration_norm_equals_svd(name):
    rs, gs = _rs_gs(h=4, w=3, channels=1, psf_shape=(3, 2))
    op = {"rolling-shutter": rs, "global-shutter": gs, "stacked": Stacked(rs, gs, psi=2.0)}[name]
    sigma = np.linalg.svd(_dense(op), compute_uv=False)[0]
    assert op.norm(iters=500, tol=1e-14) == pytest.approx(sigma, rel=1e-6)


def test_invalid_psf_and_psi_rejected():
    with pytest.raises(ValueError):
        PSFConvolution(torch.tensor([[[float("nan")]]]), (4, 4))
    rs, gs = _rs_gs()
    with pytest.raises(ValueError):
        Stacked(rs, gs, psi=-1.0)


# ----------------------------------------------------------------------------- restricted operators

ROWS, FRAMES = torch.tensor([1, 2, 6]), torch.tensor([0, 3, 4, 7])


@pytest.mark.parametrize("name", ["rolling-shutter", "rolling-shutter-colour-psf"])
def test_rolling_shutter_rows_adjointness_and_partition_sum(name):
    op = OPS[name]
    c, k, h, w = op.domain_shape
    rows, frames = ROWS, FRAMES[FRAMES < k]
    x = _rand((c, len(frames), h, w), 21)
    y = _rand((c, len(rows), w), 22)
    lhs, rhs = float(inner(op.A_rows(x, rows, frames), y)), float(inner(x, op.A_rows_adjoint(y, rows, frames)))
    assert abs(lhs - rhs) <= 1e-12 * max(1.0, abs(lhs))
    # Frame subsets that partition the video sum to the full operator's rows.
    v = _rand((c, k, h, w), 23)
    parts = torch.arange(k).split(3)
    total = sum(op.A_rows(v[:, p], rows, p) for p in parts)
    torch.testing.assert_close(total, op.A(v)[:, rows], rtol=1e-12, atol=1e-12)
    # All rows and all frames: the adjoint is the full adjoint.
    b = _rand((c, h, w), 24)
    torch.testing.assert_close(op.A_rows_adjoint(b, torch.arange(h), torch.arange(k)), op.A_adjoint(b),
                               rtol=1e-12, atol=1e-12)


def test_global_shutter_frames_adjointness_and_restriction():
    op = OPS["global-shutter"]
    c, k, h, w = op.domain_shape
    g = op.weights.shape[0]
    windows, frames = torch.tensor([0, 2]), FRAMES[FRAMES < k]
    x = _rand((c, len(frames), h, w), 31)
    y = _rand((c, len(windows), h, w), 32)
    lhs = float(inner(op.A_frames(x, windows, frames), y))
    rhs = float(inner(x, op.A_frames_adjoint(y, windows, frames)))
    assert abs(lhs - rhs) <= 1e-12 * max(1.0, abs(lhs))
    v = _rand((c, k, h, w), 33)
    touched = torch.nonzero(op.weights[windows].sum(0) > 0).flatten()
    torch.testing.assert_close(op.A_frames(v[:, touched], windows, touched), op.A(v)[:, windows])
    torch.testing.assert_close(op.A_frames(v, torch.arange(g), torch.arange(k)), op.A(v))
