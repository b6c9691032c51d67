"""The plane field's batched evaluation (every scale's planes of a kind in one padded product, the decoder
as matrix products from the left) against a straightforward evaluation plane by plane."""

import pytest
import torch
import torch.nn.functional as F

from rngcam.recon.methods.stfm import fields
from rngcam.recon.methods.stfm.fields import PlaneField, field_on_grid, transfer_fields


def _interp(coords: torch.Tensor, size: int) -> torch.Tensor:
    """(n, size) linear interpolation weights, align_corners=True, border clamp, written out."""
    pos = ((coords.double() + 1) * 0.5 * (size - 1)).clamp(0, size - 1)
    m = torch.zeros(len(coords), size, dtype=torch.float64)
    for i, p in enumerate(pos.tolist()):
        left = min(int(p), size - 2)
        m[i, left] += 1 - (p - left)
        m[i, left + 1] += p - left
    return m


def reference_grid(field: PlaneField, axes, t_index=None) -> torch.Tensor:
    """The field on the product grid, plane by plane and scale by scale in float64 (the loop the batched
    path replaces): (n_y, n_x, out) or (n_t, n_y, n_x, out)."""
    outs = []
    for s in range(field.scale_count):
        feat = None
        for j, (a, b) in enumerate(field.pairs):
            plane = field.planes[s * len(field.pairs) + j][0].double()  # (F, R_b, R_a)
            m_a = _interp(axes[a], plane.shape[2])
            m_b = _interp(axes[b], plane.shape[1])
            if b == 2 and t_index is not None:
                m_b = m_b[t_index]
            sampled = m_b @ plane @ m_a.t()
            if (a, b) == (0, 1):
                sampled = sampled if field.in_dims == 2 else sampled[:, None]
            elif (a, b) == (0, 2):
                sampled = sampled[:, :, None, :]
            else:
                sampled = sampled[:, :, :, None]
            feat = sampled if feat is None else feat * sampled
        outs.append(feat)
    x = torch.cat(outs, dim=0).movedim(0, -1)
    for layer in field.decoder:
        x = F.linear(x, layer.weight.double(), layer.bias.double()) if isinstance(layer, torch.nn.Linear) \
            else layer(x)
    return x


def reference_roughness(field: PlaneField) -> torch.Tensor:
    total, count = torch.zeros((), dtype=torch.float64), 0
    for s in range(field.scale_count):
        for j, (_a, b) in enumerate(field.pairs):
            plane = field.planes[s * len(field.pairs) + j].double()
            if b == 2 and plane.shape[2] >= 3:
                d2 = plane[:, :, 2:] - 2 * plane[:, :, 1:-1] + plane[:, :, :-2]
                total, count = total + d2.square().mean(), count + 1
    return total / max(count, 1)


def _field(in_dims: int, seed: int = 0, **cfg) -> PlaneField:
    torch.manual_seed(seed)
    f = PlaneField(in_dims, 3, **cfg)
    with torch.no_grad():  # planes with structure in every direction (time planes start constant)
        for p in f.planes:
            p.copy_(torch.rand_like(p) * 1.5 - 0.25)
    return f


def _grads(field: PlaneField) -> list[torch.Tensor]:
    """Every parameter's gradient (zeros where none reached it)."""
    return [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in field.parameters()]


CONFIGS = [
    (2, {"resolutions": (4, 8, 16), "features": 4, "hidden": 8}),
    (2, {"resolutions": (5,), "features": 3, "hidden": 0}),
    (3, {"resolutions": (4, 8, 16), "time_resolutions": (3, 6, 12), "features": 4, "hidden": 8}),
    (3, {"resolutions": (2, 7), "time_resolutions": (2, 9), "features": 2, "hidden": 6, "decoder_layers": 2}),
]


@pytest.mark.parametrize("batched", [True, False])
@pytest.mark.parametrize("in_dims,cfg,picked", [(d, c, False) for d, c in CONFIGS]
                         + [(d, c, True) for d, c in CONFIGS if d == 3])
def test_batched_grid_matches_plane_by_plane(in_dims, cfg, picked, batched, monkeypatch):
    """Values and the gradients of every plane and decoder weight equal the plane-by-plane loop's, on a
    grid that is not square and overshoots [-1, 1] (border clamp), with and without t_index; batched
    (every scale in one padded product) and scale by scale (a CPU's larger grids)."""
    monkeypatch.setattr(fields, "CPU_BATCHED_MAX_SIDE", 1_000_000 if batched else 0)
    field = _field(in_dims, **cfg)
    axes = [torch.linspace(-1.1, 1.0, 13), torch.linspace(-0.9, 1.2, 9)]
    if in_dims == 3:
        axes.append(torch.linspace(-1, 1, 11))
    t_index = torch.tensor([0, 3, 4, 10]) if picked else None
    out = field_on_grid(field, axes, t_index)
    ref = reference_grid(field, axes, t_index)
    assert out.shape == ref.shape
    assert torch.allclose(out.double(), ref, rtol=1e-5, atol=1e-5)
    torch.manual_seed(1)
    weights = torch.randn(out.shape, dtype=torch.float64)
    (out.double() * weights).sum().backward()
    got = _grads(field)
    field.zero_grad(set_to_none=True)
    (reference_grid(field, axes, t_index) * weights).sum().backward()
    for g, r in zip(got, _grads(field), strict=True):
        assert torch.allclose(g.double(), r.double(), rtol=1e-4, atol=1e-5)
    assert any(float(g.abs().max()) > 0 for g in got)


@pytest.mark.parametrize("in_dims,cfg", CONFIGS)
def test_batched_roughness_matches_plane_by_plane(in_dims, cfg):
    field = _field(in_dims, **cfg)
    value = field.time_roughness()
    ref = reference_roughness(field).detach()
    assert abs(float(value.detach()) - float(ref)) <= 1e-5 * max(1.0, abs(float(ref)))
    if in_dims == 2:
        assert float(value.detach()) == 0.0
        return
    assert float(ref) > 0
    value.backward()
    got = _grads(field)
    assert float(field.planes_time.grad.abs().max()) > 0
    field.zero_grad(set_to_none=True)
    reference_roughness(field).backward()
    for g, r in zip(got, _grads(field), strict=True):
        assert torch.allclose(g.double(), r.double(), rtol=1e-4, atol=1e-7)


def test_roughness_skips_time_planes_under_three_frames():
    """Planes of two frames have no second difference: the mean is over the others only."""
    field = _field(3, resolutions=(3, 5), time_resolutions=(2, 6), features=2, hidden=4)
    assert abs(float(field.time_roughness().detach()) - float(reference_roughness(field).detach())) < 1e-6
    only_two = _field(3, resolutions=(3, 5), time_resolutions=(2, 2), features=2, hidden=4)
    assert float(only_two.time_roughness()) == 0.0


def test_planes_are_views_of_padded_parameters_whose_padding_stays_zero():
    """Each plane keeps its own size as a view; an Adam step on a loss of grid values, the roughness
    and the pointwise path moves the planes and leaves the padding of the larger scales' size at zero."""
    a = _field(3, seed=2, resolutions=(4, 8), time_resolutions=(3, 5), features=2, hidden=4)
    assert [tuple(p.shape) for p in a.planes] == [(1, 2, 4, 4), (1, 2, 3, 4), (1, 2, 3, 4),
                                                    (1, 2, 8, 8), (1, 2, 5, 8), (1, 2, 5, 8)]
    assert {n for n, _ in a.named_parameters()} == {"planes_space", "planes_time", "decoder.0.weight",
                                                    "decoder.0.bias", "decoder.2.weight", "decoder.2.bias"}
    before = [p.detach().clone() for p in a.planes]
    opt = torch.optim.Adam(a.parameters(), lr=0.1)
    axes = [torch.linspace(-1, 1, 6), torch.linspace(-1, 1, 5), torch.linspace(-1, 1, 7)]
    for _ in range(3):
        opt.zero_grad()
        loss = field_on_grid(a, axes, torch.tensor([1, 5])).square().mean() + a.time_roughness() \
            + a(torch.rand(16, 3) * 2 - 1).square().mean()
        loss.backward()
        opt.step()
    assert all(float((p.detach() - q).abs().max()) > 0 for p, q in zip(a.planes, before, strict=True))
    padding = torch.ones_like(a.planes_space, dtype=torch.bool)
    padding[0, :, :4, :4] = False
    padding[1] = False
    assert float(a.planes_space[padding].abs().max()) == 0.0
    padding = torch.ones_like(a.planes_time, dtype=torch.bool)
    padding[0, :, :, :3, :4] = False
    padding[1] = False
    assert float(a.planes_time[padding].abs().max()) == 0.0


def test_state_dict_round_trip_and_transfer_to_other_sizes():
    a = _field(3, seed=2, resolutions=(4, 8), time_resolutions=(3, 5), features=2, hidden=4)
    b = _field(3, seed=3, resolutions=(4, 8), time_resolutions=(3, 5), features=2, hidden=4)
    b.load_state_dict(a.state_dict())
    axes = [torch.linspace(-1, 1, 6), torch.linspace(-1, 1, 5), torch.linspace(-1, 1, 7)]
    assert torch.equal(field_on_grid(a, axes), field_on_grid(b, axes))
    fine = _field(3, seed=4, resolutions=(7, 15), time_resolutions=(5, 9), features=2, hidden=4)
    transfer_fields(fine, a)
    for p, q in zip(fine.planes, a.planes, strict=True):  # each plane resampled to its own size, corners kept
        assert p.shape[-2:] != q.shape[-2:]
        assert torch.allclose(p[..., ::p.shape[-2] - 1, ::p.shape[-1] - 1], q[..., ::q.shape[-2] - 1, ::q.shape[-1] - 1])
    assert torch.allclose(field_on_grid(fine, axes).double(), reference_grid(fine, axes), rtol=1e-5, atol=1e-5)
    fewer = _field(3, seed=4, resolutions=(7,), time_resolutions=(5,), features=2, hidden=4)
    with pytest.raises(ValueError):
        transfer_fields(fewer, a)


def test_batched_grid_in_double_precision():
    """A field cast to float64 evaluates in float64 (its padding and weights cast with it)."""
    field = _field(3, resolutions=(4, 8), time_resolutions=(3, 5), features=2, hidden=4).double()
    axes = [torch.linspace(-1, 1, 6, dtype=torch.float64), torch.linspace(-1, 1, 5, dtype=torch.float64),
            torch.linspace(-1, 1, 7, dtype=torch.float64)]
    out = field_on_grid(field, axes)
    assert out.dtype == torch.float64
    assert torch.allclose(out, reference_grid(field, axes), rtol=1e-10, atol=1e-12)
    assert field.time_roughness().dtype == torch.float64
