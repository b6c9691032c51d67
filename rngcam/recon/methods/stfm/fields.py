"""Neural fields: coordinates in [-1, 1]^d -> raw features (no output activation).

Three building blocks behind one interface, `make_field(kind, in_dims, out_dims, **cfg)`:

- `PositionalEncoding`: gamma(p) = (p, sin(2^l pi p), cos(2^l pi p)) for l < n_freqs.
- `Siren` (Sitzmann et al. 2020): sine activations sin(w0 (W x + b)); first layer
  W ~ U(-1/n, 1/n), hidden and output layers W ~ U(-sqrt(6/n)/w0, sqrt(6/n)/w0), n = fan-in,
  biases as nn.Linear. Optional positional encoding in front (kind "siren" with n_freqs > 0).
- `PlaneField`: a factorised grid (K-planes / HexPlane spirit). For 3-D inputs (x, y, t) it
  keeps feature planes over xy, xt and yt at several resolutions; features are sampled
  bilinearly (grid_sample, align_corners=True, border padding), multiplied across planes
  (Hadamard product, as K-planes), concatenated across scales and decoded by a small ReLU MLP.
  A 2-D field keeps the xy plane only. Space planes start at U(0.1, 0.5) and time planes at
  one, so a 3-D field starts constant in time (as K-planes does).

Convention for coordinates: column 0 is x (image width), column 1 is y (height), column 2 is t.
With align_corners=True, -1 and +1 are the centres of the first and last pixel/frame.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rngcam.errors import ConfigError

FIELD_KINDS = ("siren", "planes")


class PositionalEncoding(nn.Module):
    """NeRF-style encoding; `out_dims` = in_dims * (1 + 2 n_freqs) (without input: 2 n_freqs)."""

    def __init__(self, in_dims: int, n_freqs: int, include_input: bool = True):
        super().__init__()
        if n_freqs < 0:
            raise ConfigError(f"positional encoding needs n_freqs >= 0, got {n_freqs}")
        self.in_dims, self.n_freqs, self.include_input = in_dims, n_freqs, include_input
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(n_freqs, dtype=torch.float32),
                             persistent=False)
        self.out_dims = in_dims * (2 * n_freqs + (1 if include_input else 0))

    def forward(self, p: Tensor) -> Tensor:
        angles = (p[..., None] * self.freqs.to(p.dtype)).flatten(-2)  # (..., d * L)
        parts = [p] if self.include_input else []
        return torch.cat(parts + [torch.sin(angles), torch.cos(angles)], dim=-1)


class SineLayer(nn.Module):
    """sin(w0 (W x + b)) with the SIREN initialisation."""

    def __init__(self, in_features: int, out_features: int, w0: float, first: bool):
        super().__init__()
        self.w0 = w0
        self.linear = nn.Linear(in_features, out_features)
        bound = 1.0 / in_features if first else math.sqrt(6.0 / in_features) / w0
        with torch.no_grad():
            self.linear.weight.uniform_(-bound, bound)

    def forward(self, x: Tensor) -> Tensor:
        return torch.sin(self.w0 * self.linear(x))


class Siren(nn.Module):
    """SIREN MLP with `layers` hidden sine layers of width `hidden` and a linear output layer."""

    def __init__(self, in_dims: int, out_dims: int, hidden: int = 128, layers: int = 3,
                 w0: float = 30.0, n_freqs: int = 0):
        super().__init__()
        if layers < 1 or hidden < 1:
            raise ConfigError(f"a SIREN needs >= 1 hidden layer of width >= 1, got {layers}x{hidden}")
        self.in_dims, self.out_dims = in_dims, out_dims
        self.encoding = PositionalEncoding(in_dims, n_freqs) if n_freqs > 0 else None
        width = self.encoding.out_dims if self.encoding is not None else in_dims
        blocks = [SineLayer(width, hidden, w0, first=True)]
        blocks += [SineLayer(hidden, hidden, w0, first=False) for _ in range(layers - 1)]
        self.body = nn.Sequential(*blocks)
        self.head = nn.Linear(hidden, out_dims)
        bound = math.sqrt(6.0 / hidden) / w0
        with torch.no_grad():
            self.head.weight.uniform_(-bound, bound)

    def forward(self, p: Tensor) -> Tensor:
        if self.encoding is not None:
            p = self.encoding(p)
        return self.head(self.body(p))


def _plane_pairs(in_dims: int) -> list[tuple[int, int]]:
    if in_dims == 2:
        return [(0, 1)]
    if in_dims == 3:
        return [(0, 1), (0, 2), (1, 2)]
    raise ConfigError(f"a plane field takes 2 (x, y) or 3 (x, y, t) input dimensions, got {in_dims}")


class PlaneField(nn.Module):
    """Multi-resolution feature planes decoded by a small MLP (see module docstring).

    `resolutions` are the spatial plane sizes per scale; `time_resolutions` the sizes of the
    t axis per scale (default: the same as `resolutions`). `hidden` = 0 gives a linear decoder.
    """

    def __init__(self, in_dims: int, out_dims: int, resolutions: Sequence[int] = (8, 16, 32),
                 time_resolutions: Sequence[int] | None = None, features: int = 8, hidden: int = 32,
                 decoder_layers: int = 1, init_range: tuple[float, float] = (0.1, 0.5)):
        super().__init__()
        self.pairs = _plane_pairs(in_dims)
        self.in_dims, self.out_dims, self.features = in_dims, out_dims, features
        time_resolutions = list(resolutions if time_resolutions is None else time_resolutions)
        if not resolutions or min(resolutions) < 2 or len(time_resolutions) != len(resolutions):
            raise ConfigError(f"plane resolutions must be >= 2 (one time resolution per scale), got "
                              f"{list(resolutions)} and {time_resolutions}")
        self.planes = nn.ParameterList()
        self.scale_count = len(resolutions)
        for res, t_res in zip(resolutions, time_resolutions):
            for _a, b in self.pairs:
                size_a = int(res)  # a is always a space axis (x or y)
                size_b = int(res) if b < 2 else max(int(t_res), 2)
                plane = torch.empty(1, features, size_b, size_a)
                if b == 2:  # a time plane: start at one, so the field is constant in time
                    nn.init.ones_(plane)
                else:
                    nn.init.uniform_(plane, *init_range)
                self.planes.append(nn.Parameter(plane))
        width = features * len(resolutions)
        layers: list[nn.Module] = []
        for _ in range(decoder_layers if hidden > 0 else 0):
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        layers.append(nn.Linear(width, out_dims))
        self.decoder = nn.Sequential(*layers)

    def encode(self, p: Tensor) -> Tensor:
        """Plane features (N, features * scales) at coordinates p (N, in_dims)."""
        n = p.shape[0]
        outs = []
        for s in range(self.scale_count):
            feat = None
            for j, (a, b) in enumerate(self.pairs):
                plane = self.planes[s * len(self.pairs) + j]
                grid = torch.stack([p[:, a], p[:, b]], dim=-1).view(1, n, 1, 2).to(plane.dtype)
                sampled = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border",
                                        align_corners=True).view(self.features, n)
                feat = sampled if feat is None else feat * sampled
            outs.append(feat)
        return torch.cat(outs, dim=0).t()

    def forward(self, p: Tensor) -> Tensor:
        return self.decoder(self.encode(p))

    def time_roughness(self) -> Tensor:
        """Mean squared second difference of the time planes along t (K-planes' temporal
        smoothness); zero for a 2-D field."""
        total = torch.zeros((), device=self.planes[0].device)
        count = 0
        for s in range(self.scale_count):
            for j, (_a, b) in enumerate(self.pairs):
                plane = self.planes[s * len(self.pairs) + j]
                if b == 2 and plane.shape[2] >= 3:
                    d2 = plane[:, :, 2:] - 2 * plane[:, :, 1:-1] + plane[:, :, :-2]
                    total = total + d2.square().mean()
                    count += 1
        return total / max(count, 1)

    def forward_grid(self, axes: Sequence[Tensor], t_index: Tensor | None = None) -> Tensor:
        """The field on the Cartesian product of 1-D coordinate vectors (x, y[, t]).

        Returns (n_y, n_x, out) or (n_t, n_y, n_x, out). Same values as `forward` on the
        meshgrid, but each plane is sampled with two small interpolation matrices instead of
        grid_sample: much faster, forward and backward, on a CPU. `t_index`: the frames
        axes[2][t_index] only (the time axis's matrix is built once and its rows picked).
        """
        if len(axes) != self.in_dims:
            raise ValueError(f"expected {self.in_dims} coordinate vectors, got {len(axes)}")
        outs = []
        for s in range(self.scale_count):
            feat = None
            for j, (a, b) in enumerate(self.pairs):
                plane = self.planes[s * len(self.pairs) + j][0]  # (F, R_b, R_a)
                m_a = _interp_matrix(axes[a], plane.shape[2], plane.dtype)
                m_b = _interp_matrix(axes[b], plane.shape[1], plane.dtype)
                if b == 2 and t_index is not None:
                    m_b = m_b.index_select(0, t_index)
                sampled = m_b @ plane @ m_a.t()  # (F, n_b, n_a)
                if (a, b) == (0, 1):
                    sampled = sampled if self.in_dims == 2 else sampled[:, None]  # (F, [1,] n_y, n_x)
                elif (a, b) == (0, 2):
                    sampled = sampled[:, :, None, :]  # (F, n_t, 1, n_x)
                else:
                    sampled = sampled[:, :, :, None]  # (F, n_t, n_y, 1)
                feat = sampled if feat is None else feat * sampled
            outs.append(feat)
        feats = torch.cat(outs, dim=0)
        return self.decoder(feats.movedim(0, -1))


def translate_image(image: Tensor, axes: Sequence[Tensor], shifts: Tensor) -> Tensor:
    """An image (R_y, R_x, out) on linspace(-1, 1) knots, interpolated bilinearly (border clamp) at
    the pixel grid (x, y) moved by `shifts` (n, 2) in coordinate units: (n, n_y, n_x, out). One
    interpolation matrix per frame and axis, two matrix products. (STFM's prior preset decodes its
    canonical image once a step on `knots` half a pixel apart and moves it so; bench/convergence.md, "the
    prior preset decodes its canonical image once a step".)"""
    xs, ys = axes
    n, nx, ny = shifts.shape[0], xs.shape[0], ys.shape[0]
    ry, rx, out = image.shape
    m_x = _build_interp_matrix((xs[None] + shifts[:, :1]).reshape(-1), rx, image.dtype)  # (n n_x, R_x)
    m_y = _build_interp_matrix((ys[None] + shifts[:, 1:]).reshape(-1), ry, image.dtype).view(n, ny, ry)
    along_x = (image.permute(2, 0, 1).reshape(out * ry, rx) @ m_x.t()).view(out, ry, n, nx)
    moved = torch.bmm(m_y, along_x.permute(2, 1, 0, 3).reshape(n, ry, out * nx)).view(n, ny, out, nx)
    return moved.permute(0, 1, 3, 2)


def knots(axis: Tensor, spacing: float) -> Tensor:
    """linspace(-1, 1) knots about `spacing` pixels apart along a pixel axis (linspace(-1, 1, n)):
    coarser (spacing > 1: the axis itself where that is no coarser) or finer (spacing 1/k: the pixel
    centres on them; an axis of one pixel spans -1 to 1 with its centre on the middle knot)."""
    n = axis.shape[0]
    if spacing >= 1:
        count = (n - 1) // round(spacing) + 1
        if count < 2 or count >= n:
            return axis
    else:
        count = round((max(n, 2) - 1) / spacing) + 1
    return torch.linspace(-1.0, 1.0, count, device=axis.device, dtype=axis.dtype)


def interpolate_grid(values: Tensor, knots: Sequence[Tensor], axes: Sequence[Tensor]) -> Tensor:
    """values (..., R_y, R_x, out) on the knots (x, y), interpolated bilinearly (border clamp) at
    the points of the axes (x, y): (..., n_y, n_x, out)."""
    if all(k is a for k, a in zip(knots, axes)):
        return values
    m_x = _interp_matrix(axes[0], knots[0].shape[0], values.dtype)  # (n_x, R_x)
    m_y = _interp_matrix(axes[1], knots[1].shape[0], values.dtype)  # (n_y, R_y)
    # beats two matmuls (bench/convergence.md, "the fast preset's motion on knots")
    return torch.einsum("yj,...jic,xi->...yxc", m_y, values, m_x)


# id(coordinate vector) -> (weak reference, its version, {(size, dtype): matrix}): the pixel and
# frame axes repeat every step. Keyed by the tensor itself, not its values: reading the values
# would wait for a GPU at every call.
_MATRIX_CACHE: dict[int, tuple] = {}


def _interp_matrix(coords: Tensor, size: int, dtype) -> Tensor:
    """(n, size) matrix of 1-D linear interpolation weights, align_corners=True, border clamp.

    Matrices for coordinate vectors that do not need a gradient are kept while the vector lives
    and is not changed in place."""
    if coords.requires_grad:
        return _build_interp_matrix(coords, size, dtype)
    key = id(coords)
    entry = _MATRIX_CACHE.get(key)
    if entry is None or entry[0]() is not coords or entry[1] != coords._version:
        entry = _MATRIX_CACHE[key] = (weakref.ref(coords, lambda _ref, k=key: _MATRIX_CACHE.pop(k, None)),
                                      coords._version, {})
    m = entry[2].get((size, dtype))
    if m is None:
        m = entry[2][(size, dtype)] = _build_interp_matrix(coords, size, dtype)
    return m


def _build_interp_matrix(coords: Tensor, size: int, dtype) -> Tensor:
    pos = ((coords.to(dtype) + 1) * 0.5 * (size - 1)).clamp(0, size - 1)
    left = pos.floor().clamp(max=size - 2).long()
    frac = pos - left
    m = torch.zeros(coords.shape[0], size, dtype=dtype, device=coords.device)
    rows = torch.arange(coords.shape[0], device=coords.device)
    m[rows, left] = 1 - frac
    m[rows, left + 1] = frac
    return m


def field_on_grid(field: nn.Module, axes: Sequence[Tensor], t_index: Tensor | None = None) -> Tensor:
    """Evaluate any field on the product grid of 1-D coordinates (x, y[, t]) (`t_index`: at
    axes[2][t_index] only).

    Returns (n_y, n_x, out) for 2-D fields and (n_t, n_y, n_x, out) for 3-D fields; uses the
    fast separable path of a PlaneField and a meshgrid otherwise.
    """
    if hasattr(field, "forward_grid"):
        return field.forward_grid(axes, t_index)
    if t_index is not None:
        axes = [*axes[:2], axes[2][t_index]]
    grids = torch.meshgrid(*reversed(list(axes)), indexing="ij")  # ([t,] y, x)
    p = torch.stack([g.reshape(-1) for g in reversed(grids)], dim=-1)
    return field(p).reshape(*grids[0].shape, -1)


def make_field(kind: str, in_dims: int, out_dims: int, **cfg) -> nn.Module:
    """A field of `kind` ("siren" or "planes") from in_dims coordinates to out_dims raw outputs.

    `cfg` goes to the class: Siren(hidden, layers, w0, n_freqs) or
    PlaneField(resolutions, time_resolutions, features, hidden, decoder_layers).
    """
    if in_dims not in (2, 3):
        raise ConfigError(f"fields take 2 (x, y) or 3 (x, y, t) coordinates, got {in_dims}")
    try:
        if kind == "siren":
            return Siren(in_dims, out_dims, **cfg)
        if kind == "planes":
            return PlaneField(in_dims, out_dims, **cfg)
    except TypeError as exc:
        raise ConfigError(f"bad settings for a {kind} field: {exc}") from None
    raise ConfigError(f"unknown field kind {kind!r} (choose from {', '.join(FIELD_KINDS)})")


def transfer_fields(target: nn.Module, source: nn.Module) -> None:
    """Copy `source`'s fields into `target` (same kinds, scales and features): feature planes
    resampled bilinearly to the target's plane sizes (corners aligned: plane coordinates span
    [-1, 1] on every grid), every other parameter copied. ValueError if they do not match."""
    src, dst = dict(source.named_parameters()), dict(target.named_parameters())
    if src.keys() != dst.keys():
        raise ValueError("fields differ in structure")
    with torch.no_grad():
        for name, p in dst.items():
            q = src[name].to(p)
            if q.shape == p.shape:
                p.copy_(q)
            elif q.ndim == 4 and q.shape[:2] == p.shape[:2]:
                p.copy_(F.interpolate(q, size=p.shape[-2:], mode="bilinear", align_corners=True))
            else:
                raise ValueError(f"field parameter {name}: {tuple(q.shape)} cannot become {tuple(p.shape)}")
