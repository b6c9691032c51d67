"""Neural fields: positional encoding, SIREN initialisation, factorised plane fields."""

import math

import pytest
import torch

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm.fields import (
    PlaneField,
    PositionalEncoding,
    Siren,
    field_on_grid,
    interpolate_grid,
    knots,
    make_field,
    translate_image,
)


def test_positional_encoding_values_and_size():
    pe = PositionalEncoding(2, n_freqs=3)
    p = torch.tensor([[0.25, -0.5]])
    out = pe(p)
    assert out.shape == (1, 2 * (1 + 2 * 3)) == (1, pe.out_dims)
    assert torch.allclose(out[0, :2], p[0])
    # sin block: (dim0 f0, dim0 f1, dim0 f2, dim1 f0, ...), then the cos block
    expected_sin = torch.tensor([math.sin(math.pi * 2 ** f * x) for x in (0.25, -0.5) for f in range(3)])
    expected_cos = torch.tensor([math.cos(math.pi * 2 ** f * x) for x in (0.25, -0.5) for f in range(3)])
    assert torch.allclose(out[0, 2:8], expected_sin, atol=1e-6)
    assert torch.allclose(out[0, 8:], expected_cos, atol=1e-6)


def test_siren_published_initialisation():
    torch.manual_seed(0)
    w0, hidden = 30.0, 256
    net = Siren(3, 4, hidden=hidden, layers=3, w0=w0)
    first = net.body[0].linear.weight
    assert first.abs().max() <= 1 / 3 and first.abs().max() > 0.9 / 3  # U(-1/n, 1/n), n = 3
    for layer in list(net.body)[1:]:
        w = layer.linear.weight
        bound = math.sqrt(6 / hidden) / w0
        assert w.abs().max() <= bound and w.abs().max() > 0.95 * bound
        assert abs(float(w.detach().std()) - bound / math.sqrt(3)) < 0.05 * bound  # uniform spread
    assert net.body[0].w0 == w0
    # activations keep the arcsine distribution through depth (the point of the init)
    x = torch.rand(4096, 3) * 2 - 1
    with torch.no_grad():
        h = net.body(x)
    assert 0.5 < float(h.std()) < 0.9


def test_siren_with_encoding_takes_encoded_width():
    net = Siren(2, 3, hidden=16, layers=2, n_freqs=4)
    assert net.body[0].linear.in_features == 2 * 9
    assert net(torch.zeros(5, 2)).shape == (5, 3)


@pytest.mark.parametrize("in_dims", [2, 3])
def test_plane_field_grid_path_matches_pointwise(in_dims):
    torch.manual_seed(1)
    f = PlaneField(in_dims, 3, resolutions=(4, 7), time_resolutions=(3, 5), features=4, hidden=8).double()
    with torch.no_grad():
        for plane in f.planes:  # break the constant-in-time start so t matters
            plane.uniform_(-1, 1)
    axes = [torch.linspace(-1, 1, 9, dtype=torch.float64), torch.linspace(-1.2, 1, 6, dtype=torch.float64)]
    if in_dims == 3:
        axes.append(torch.tensor([-1.0, -0.3, 0.4, 1.0], dtype=torch.float64))
    grid = f.forward_grid(axes)
    mesh = torch.meshgrid(*reversed(axes), indexing="ij")
    p = torch.stack([m.reshape(-1) for m in reversed(mesh)], dim=-1)
    pointwise = f(p).reshape(grid.shape)
    assert torch.allclose(grid, pointwise, atol=1e-12)


def test_plane_field_samples_corners_exactly():
    f = PlaneField(2, 1, resolutions=(5,), features=2, hidden=0)
    plane = f.planes[0]
    corners = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
    feats = f.encode(corners)
    expected = torch.stack([plane[0, :, 0, 0], plane[0, :, 0, -1], plane[0, :, -1, 0], plane[0, :, -1, -1]])
    assert torch.allclose(feats, expected)


def test_three_d_plane_field_starts_constant_in_time():
    f = PlaneField(3, 2, resolutions=(4, 8), features=4, hidden=8)
    out = field_on_grid(f, [torch.linspace(-1, 1, 5), torch.linspace(-1, 1, 5), torch.linspace(-1, 1, 7)])
    assert out.shape == (7, 5, 5, 2)
    assert torch.allclose(out, out[:1].expand_as(out), atol=1e-6)
    assert float(out[0].detach().std()) > 0  # but not constant in space


@pytest.mark.parametrize("kind,cfg", [("siren", {"hidden": 16, "layers": 2, "n_freqs": 2}),
                                      ("planes", {"resolutions": (4, 8), "features": 4, "hidden": 8})])
def test_every_parameter_gets_a_gradient(kind, cfg):
    torch.manual_seed(2)
    f = make_field(kind, 3, 2, **cfg)
    with torch.no_grad():
        for p in f.parameters():
            p.add_(0.1 * torch.randn_like(p))
    p = torch.rand(200, 3) * 2 - 1
    f(p).square().sum().backward()
    for name, param in f.named_parameters():
        assert param.grad is not None and float(param.grad.abs().sum()) > 0, name


def test_field_on_grid_generic_path_for_siren():
    f = make_field("siren", 2, 3, hidden=8, layers=1)
    xs, ys = torch.linspace(-1, 1, 4), torch.linspace(-1, 1, 3)
    out = field_on_grid(f, [xs, ys])
    assert out.shape == (3, 4, 3)
    assert torch.allclose(out[2, 1], f(torch.tensor([[xs[1], ys[2]]]))[0])


def test_bad_configuration_is_a_clear_error():
    with pytest.raises(ConfigError, match="unknown field kind"):
        make_field("hash", 2, 3)
    with pytest.raises(ConfigError, match="coordinates"):
        make_field("planes", 4, 3)
    with pytest.raises(ConfigError, match="bad settings"):
        make_field("siren", 2, 3, width=3)
    with pytest.raises(ConfigError, match="resolutions"):
        make_field("planes", 2, 3, resolutions=(1,))


def test_grid_path_at_frame_indices_matches_those_frames_and_reuses_the_axes_matrices():
    from rngcam.recon.methods.stfm import fields

    torch.manual_seed(2)
    f = PlaneField(3, 2, resolutions=(4, 6), time_resolutions=(5, 3), features=3, hidden=8).double()
    with torch.no_grad():
        for plane in f.planes:
            plane.uniform_(-1, 1)
    xs, ys, ts = (torch.linspace(-1, 1, n, dtype=torch.float64) for n in (7, 5, 9))
    idx = torch.tensor([0, 3, 3, 8])
    picked = field_on_grid(f, [xs, ys, ts], idx)
    assert torch.allclose(picked, field_on_grid(f, [xs, ys, ts[idx]]), atol=1e-12)
    # the axes' matrices are kept while the axes live and are unchanged, rebuilt once changed in place
    m = fields._interp_matrix(ts, 5, torch.float64)
    assert fields._interp_matrix(ts, 5, torch.float64) is m
    ts[0] = -0.5
    again = fields._interp_matrix(ts, 5, torch.float64)
    assert again is not m and float(again[0].sum()) == pytest.approx(1.0)
    assert torch.allclose(again, fields._build_interp_matrix(ts, 5, torch.float64))
    key = id(ts)
    del ts, again
    assert key not in fields._MATRIX_CACHE  # a dead axis leaves nothing behind


def test_translated_path_is_the_decoded_image_moved_bilinearly():
    """The field on knots half a pixel apart, then translate_image (STFM's one translation per frame): the field
    decoded on a grid twice as fine as the pixels, moved per frame by bilinear interpolation with a
    border clamp, values and
    gradients (planes, decoder and shifts) as grid_sample gives them on that image; at the pixels
    themselves and at moves by whole knots, what `forward` gives at the moved points."""
    torch.manual_seed(2)
    f = PlaneField(2, 3, resolutions=(4, 7, 9), features=3, hidden=8).double()
    with torch.no_grad():
        for plane in f.planes:
            plane.uniform_(-1, 1)
    xs, ys = torch.linspace(-1, 1, 9, dtype=torch.float64), torch.linspace(-1, 1, 6, dtype=torch.float64)
    # some points moved off the grid; none exactly onto its edge, where grid_sample's coordinate
    # gradient takes the slope towards the zeros outside and the matrices the slope inside
    shifts = torch.tensor([[0.01, -0.02], [0.13, -0.41], [-0.9, 0.3], [1.7, -1.55]], dtype=torch.float64)

    def pointwise(x, y):
        return f(torch.stack([x, y], dim=-1).reshape(-1, 2)).reshape(*x.shape, 3)

    def moved_image(axes, s):
        return translate_image(f.forward_grid([knots(a, 0.5) for a in axes]), axes, s)

    def moved(s):
        x = (xs[None, None, :] + s[:, 0, None, None]).expand(len(s), len(ys), len(xs))
        y = (ys[None, :, None] + s[:, 1, None, None]).expand(len(s), len(ys), len(xs))
        return x, y

    def reference(s):
        kx, ky = torch.linspace(-1, 1, 17, dtype=torch.float64), torch.linspace(-1, 1, 11, dtype=torch.float64)
        gy, gx = torch.meshgrid(ky, kx, indexing="ij")
        image = pointwise(gx, gy).permute(2, 0, 1)[None].expand(len(s), 3, 11, 17)
        x, y = moved(s)
        out = torch.nn.functional.grid_sample(image, torch.stack([x, y], dim=-1), mode="bilinear",
                                              padding_mode="border", align_corners=True)
        return out.permute(0, 2, 3, 1)

    def both(path):
        s = shifts.clone().requires_grad_()
        out = path(s)
        weights = torch.linspace(-1, 2, out.numel(), dtype=torch.float64).view_as(out)
        grads = torch.autograd.grad((out * weights).sum(), [s, *f.parameters()])
        return out.detach(), grads

    fast, fast_grads = both(lambda s: moved_image([xs, ys], s))
    slow, slow_grads = both(reference)
    assert fast.shape == (4, 6, 9, 3)
    assert torch.allclose(fast, slow, atol=1e-12)
    for a, b in zip(fast_grads, slow_grads, strict=True):
        assert torch.allclose(a, b, atol=1e-10)
    assert fast_grads[0][1].abs().sum() > 0  # a shift inside the grid moves the output
    with torch.no_grad():  # on the knots the image is the field itself: no shift, and whole knots
        whole = torch.tensor([[0.0, 0.0], [2 / 16, -3 * 2 / 10], [-5 * 2 / 16, 2 / 10]], dtype=torch.float64)
        assert torch.allclose(moved_image([xs, ys], whole), pointwise(*moved(whole)), atol=1e-12)
        # an axis of one pixel: its centre stays on the grid
        one = moved_image([torch.zeros(1, dtype=torch.float64), ys], whole[:1])
        assert torch.allclose(one, pointwise(*torch.meshgrid(torch.zeros(1, dtype=torch.float64), ys,
                                                             indexing="xy"))[None], atol=1e-12)
    with pytest.raises(ValueError):
        PlaneField(3, 2).forward_grid([knots(a, 0.5) for a in (xs, ys)])


def test_values_on_knots_are_interpolated_bilinearly_at_the_pixels():
    """interpolate_grid (STFM's motion field, decoded on knots about every 2 px): values and their
    gradient as grid_sample gives them on the knots' image; a pixel on a knot reads that knot."""
    torch.manual_seed(3)
    xs, ys = torch.linspace(-1, 1, 33, dtype=torch.float64), torch.linspace(-1, 1, 19, dtype=torch.float64)
    kx, ky = knots(xs, 2), knots(ys, 2)
    assert (len(kx), len(ky)) == (17, 10) and kx[0] == -1 and kx[-1] == 1
    values = torch.randn(4, len(ky), len(kx), 2, dtype=torch.float64, requires_grad=True)
    out = interpolate_grid(values, [kx, ky], [xs, ys])
    grid = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1], dim=-1)[None].expand(4, -1, -1, -1)
    ref = torch.nn.functional.grid_sample(values.permute(0, 3, 1, 2), grid, mode="bilinear",
                                          padding_mode="border", align_corners=True).permute(0, 2, 3, 1)
    assert out.shape == (4, 19, 33, 2)
    assert torch.allclose(out, ref, atol=1e-12)
    weights = torch.linspace(-1, 2, out.numel(), dtype=torch.float64).view_as(out)
    got, = torch.autograd.grad((out * weights).sum(), values)
    want, = torch.autograd.grad((ref * weights).sum(), values)
    assert torch.allclose(got, want, atol=1e-12)
    assert torch.allclose(out[:, ::2, ::2], values, atol=1e-12)  # every other pixel is a knot here
    # axes too short to thin are their own knots, passed through untouched
    two = torch.linspace(-1, 1, 2)
    assert knots(two, 2) is two and knots(torch.zeros(1), 2).shape == (1,)
    same = torch.randn(3, 2, 2, 1)
    assert interpolate_grid(same, [two, two], [two, two]) is same
