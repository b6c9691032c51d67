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

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm.decoder import decode

FIELD_KINDS = ("siren", "planes")
# A plane field's scales are sampled in one product, their planes zero-padded to the largest (a few
# operations a call: what a GPU and a small grid want), on a GPU always and on a CPU where the largest
# plane side is at most this; larger grids on a CPU sample scale by scale, where the padded arithmetic
# would cost more than the operations saved (bench/step_ops.md).
CPU_BATCHED_MAX_SIDE = 96


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

    Every scale's planes of a kind are one parameter, zero-padded to the largest scale's size, so that
    a grid evaluation is a few batched matrix products whatever the scales: `planes_space` (S, F, R, R),
    the xy planes (y, x), and for a 3-D field `planes_time` (S, 2, F, T, R), the xt and yt planes (t,
    space). The padding stays zero: the interpolation matrices' padded columns are zero, so no gradient
    reaches it. `planes` lists each plane as a view (1, F, R_b, R_a), scale by scale and pair by pair.
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
        self.scale_count = len(resolutions)
        self.space_sizes = [int(res) for res in resolutions]  # a is always a space axis (x or y)
        self.time_sizes = [max(int(t_res), 2) for t_res in time_resolutions]
        r, t, s = max(self.space_sizes), max(self.time_sizes), self.scale_count
        self.planes_space = nn.Parameter(torch.zeros(s, features, r, r))
        self.register_parameter("planes_time", nn.Parameter(torch.zeros(s, 2, features, t, r)) if in_dims == 3
                                else None)
        with torch.no_grad():
            for plane, (_a, b) in zip(self.planes, self.pairs * s):  # drawn plane by plane, as one parameter each
                if b == 2:  # a time plane: start at one, so the field is constant in time
                    plane.fill_(1.0)
                else:
                    plane.copy_(nn.init.uniform_(torch.empty(plane.shape), *init_range))
        width = features * len(resolutions)
        layers: list[nn.Module] = []
        for _ in range(decoder_layers if hidden > 0 else 0):
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        layers.append(nn.Linear(width, out_dims))
        self.decoder = nn.Sequential(*layers)
        self.register_buffer("_roughness", self._roughness_weights(), persistent=False)
        t = max(self.time_sizes)
        self.register_buffer("_second_difference", None if self._roughness is None else
                             torch.eye(t)[2:] - 2 * torch.eye(t)[1:-1] + torch.eye(t)[:-2], persistent=False)

    @property
    def planes(self) -> list[Tensor]:
        """Each plane (1, F, R_b, R_a), a view of its parameter, scale by scale and pair by pair."""
        out = []
        for s, (res, t_res) in enumerate(zip(self.space_sizes, self.time_sizes)):
            for j, (_a, b) in enumerate(self.pairs):
                out.append(self.planes_space[s:s + 1, :, :res, :res] if b < 2
                           else self.planes_time[s, j - 1:j, :, :t_res, :res])
        return out

    def encode(self, p: Tensor) -> Tensor:
        """Plane features (N, features * scales) at coordinates p (N, in_dims)."""
        n = p.shape[0]
        outs = []
        planes = self.planes
        for s in range(self.scale_count):
            feat = None
            for j, (a, b) in enumerate(self.pairs):
                plane = planes[s * len(self.pairs) + j]
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
        smoothness; the mean over the time planes of at least 3 frames of each one's mean); zero
        for a 2-D field."""
        if self._roughness is None:
            return torch.zeros((), device=self.planes_space.device)
        p = self.planes_time
        s, _, f, t, r = p.shape
        # second differences along t as one batched product (slices and their backward cost more operations)
        d2 = torch.bmm(self._second_difference.expand(s * 2 * f, t - 2, t), p.view(s * 2 * f, t, r))
        return (d2.view(s, 2, f, t - 2, r).square() * self._roughness).sum()

    def _roughness_weights(self) -> Tensor | None:
        """(S, 2, 1, T - 2, R) weights of the padded time planes' squared second differences: one over
        (the planes of >= 3 frames times a plane's differences) where a plane has them, else zero
        (None: no such plane)."""
        count = 2 * sum(t >= 3 for t in self.time_sizes)
        if self.in_dims == 2 or count == 0:
            return None
        w = torch.zeros(self.scale_count, 2, 1, max(self.time_sizes) - 2, max(self.space_sizes))
        for s, (res, t_res) in enumerate(zip(self.space_sizes, self.time_sizes)):
            if t_res >= 3:
                w[s, :, :, :t_res - 2, :res] = 1.0 / (count * self.features * (t_res - 2) * res)
        return w

    def forward_grid(self, axes: Sequence[Tensor], t_index: Tensor | None = None) -> Tensor:
        """The field on the Cartesian product of 1-D coordinate vectors (x, y[, t]).

        Returns (n_y, n_x, out) or (n_t, n_y, n_x, out). Same
        values as `forward` on the meshgrid, but each plane is sampled with two small
        interpolation matrices instead of grid_sample: much faster, forward and backward, on a CPU.
        Every scale's planes of a kind are sampled in one batched product (scale by scale on a
        CPU past CPU_BATCHED_MAX_SIDE), the decoder two matrix products on all points: a call is
        a few dozen operations. `t_index`: the frames
        axes[2][t_index] only (the time axis's matrix is built once and its rows picked).
        """
        if len(axes) != self.in_dims:
            raise ValueError(f"expected {self.in_dims} coordinate vectors, got {len(axes)}")
        batched = self.planes_space.device.type != "cpu" or max(self.space_sizes) <= CPU_BATCHED_MAX_SIDE
        feats = self._features_batched(axes, t_index) if batched else self._features_by_scale(axes, t_index)
        # decoded on the features' transposed view, (points, S F): no copy, and faster than from the left
        return decode(self.decoder, feats.view(feats.shape[0], -1).t()).view(*feats.shape[1:], -1)

    def _features_batched(self, axes: Sequence[Tensor], t_index: Tensor | None) -> Tensor:
        """Features (S F, [n_t,] n_y, n_x): every scale's planes of a kind in one product."""
        xs, ys = axes[0], axes[1]
        s, f, (r, n_x, n_y) = self.scale_count, self.features, (self.planes_space.shape[-1], len(xs), len(ys))
        dtype = self.planes_space.dtype
        m_x = _stacked_interp(xs, self.space_sizes, r, n_x, dtype)  # (S, n_x, R)
        m_y = _stacked_interp(ys, self.space_sizes, r, n_y, dtype, repeat=f)  # (S F, n_y, R)
        along_x = torch.bmm(self.planes_space.view(s, f * r, r), m_x.mT)  # (S, F R_y, n_x)
        feats = torch.bmm(m_y, along_x.view(s * f, r, n_x))  # (S F, n_y, n_x)
        if self.in_dims == 2:
            return feats
        t_all, t = axes[2], self.planes_time.shape[3]
        n = max(n_x, n_y)  # xt and yt in one product: the shorter space axis zero-padded
        m_t = _stacked_interp(t_all, self.time_sizes, t, len(t_all), dtype, repeat=2 * f)  # (S 2 F, K, T)
        if t_index is not None:
            m_t = m_t.index_select(1, t_index)
        n_t = m_t.shape[1]
        m_s = torch.stack([_stacked_interp(xs, self.space_sizes, r, n, dtype),
                           _stacked_interp(ys, self.space_sizes, r, n, dtype)], dim=1)  # (S, 2, n, R)
        along_t = torch.bmm(m_t, self.planes_time.view(s * 2 * f, t, r))  # (S 2 F, n_t, R)
        time = torch.bmm(along_t.view(s * 2, f * n_t, r), m_s.view(s * 2, n, r).mT).view(s, 2, f, n_t, n)
        feats = (feats.view(s, f, 1, n_y, n_x) * time[:, 0, :, :, None, :n_x]) * time[:, 1, :, :, :n_y, None]
        return feats.view(s * f, n_t, n_y, n_x)

    def _features_by_scale(self, axes: Sequence[Tensor], t_index: Tensor | None) -> Tensor:
        """Features (S F, [n_t,] n_y, n_x), scale by scale on the planes' own sizes (no padded work)."""
        xs, ys = axes[0], axes[1]
        dtype = self.planes_space.dtype
        outs = []
        for s, (res, t_res) in enumerate(zip(self.space_sizes, self.time_sizes)):
            m_x, m_y = _interp_matrix(xs, res, dtype), _interp_matrix(ys, res, dtype)
            feat = m_y @ self.planes_space[s, :, :res, :res] @ m_x.t()  # (F, n_y, n_x)
            if self.in_dims == 3:
                m_t = _interp_matrix(axes[2], t_res, dtype)
                if t_index is not None:
                    m_t = m_t.index_select(0, t_index)
                xt = m_t @ self.planes_time[s, 0, :, :t_res, :res] @ m_x.t()  # (F, n_t, n_x)
                yt = m_t @ self.planes_time[s, 1, :, :t_res, :res] @ m_y.t()  # (F, n_t, n_y)
                feat = (feat[:, None] * xt[:, :, None, :]) * yt[:, :, :, None]
            outs.append(feat)
        return torch.cat(outs)


def translate_image(image: Tensor, axes: Sequence[Tensor], shifts: Tensor) -> Tensor:
    """An image (R_y, R_x, out) on linspace(-1, 1) knots, interpolated bilinearly (border clamp) at
    the pixel grid (x, y) moved by `shifts` (n, 2) in coordinate units: (n, n_y, n_x, out). One
    interpolation matrix per frame and axis (both axes' built at once where they have the same sizes),
    two matrix products. (STFM's prior preset decodes its canonical image once a step on `knots` half
    a pixel apart and moves it so; bench/convergence.md, "the prior preset decodes its canonical image
    once a step".)"""
    xs, ys = axes
    n, nx, ny = shifts.shape[0], xs.shape[0], ys.shape[0]
    ry, rx, out = image.shape
    if rx == ry and nx == ny:
        m_x, m_y = _interp_weights(torch.stack([xs, ys])[:, None] + shifts.t()[:, :, None], rx, image.dtype).unbind(0)
    else:
        m_x = _interp_weights(xs[None] + shifts[:, :1], rx, image.dtype)
        m_y = _interp_weights(ys[None] + shifts[:, 1:], ry, image.dtype)
    along_x = (image.permute(2, 0, 1).reshape(out * ry, rx) @ m_x.reshape(n * nx, rx).t()).view(out, ry, n, nx)
    moved = torch.bmm(m_y, along_x.permute(2, 1, 0, 3).reshape(n, ry, out * nx)).view(n, ny, out, nx)
    return moved.permute(0, 1, 3, 2)


# (size, dtype, device) -> translate_image's constants on that device (`_interp_constants`)
_KNOT_CONSTANTS: dict[tuple, tuple[Tensor, ...]] = {}


def _interp_constants(size: int, dtype, device) -> tuple[Tensor, ...]:
    """(the knots' indices, 0, 1, -1, (size - 1) / 2, size - 1, size - 2) as tensors: a factor given as a
    number costs a conversion each time, forward and backward."""
    key = (size, dtype, device)
    if key not in _KNOT_CONSTANTS:
        values = (0.0, 1.0, -1.0, 0.5 * (size - 1), size - 1, size - 2)
        _KNOT_CONSTANTS[key] = (torch.arange(size, dtype=dtype, device=device),
                                *(torch.tensor(v, dtype=dtype, device=device) for v in values))
    return _KNOT_CONSTANTS[key]


def _interp_weights(coords: Tensor, size: int, dtype) -> Tensor:
    """(..., size) linear interpolation weights of `coords` (...) on `size` knots, align_corners=True,
    border clamp, with their gradient: `_build_interp_matrix`'s values as the left knot's indicator plus
    the fraction times (right indicator - left indicator) (no index_put: a few operations, forward and
    backward, whatever the shape)."""
    knot, zero, one, minus_one, half_span, last, last_left = _interp_constants(size, dtype, coords.device)
    pos = torch.clamp((coords.to(dtype) + one) * half_span, zero, last)
    left = torch.minimum(pos.detach().floor(), last_left)
    offset = knot - left[..., None]
    at_left = offset == zero
    indicator = torch.where(at_left, one, zero)
    step = torch.where(offset == one, one, torch.where(at_left, minus_one, zero))
    return torch.addcmul(indicator, (pos - left)[..., None], step)


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
    the points of the axes (x, y): (..., n_y, n_x, out) (a view of channels-first storage)."""
    if all(k is a for k, a in zip(knots, axes)):
        return values
    m_x = _interp_matrix(axes[0], knots[0].shape[0], values.dtype)  # (n_x, R_x)
    m_y = _interp_matrix(axes[1], knots[1].shape[0], values.dtype)  # (n_y, R_y)
    *lead, ry, rx, out = values.shape
    # channels first, then two batched products with the matrices broadcast: fewer operations and no more
    # time than one einsum (bench/step_ops.md)
    v = values.movedim(-1, -3).reshape(-1, ry, rx)
    along_x = torch.bmm(v, m_x.t().expand(v.shape[0], rx, m_x.shape[0]))
    moved = torch.bmm(m_y.expand(v.shape[0], *m_y.shape), along_x)
    return moved.view(*lead, out, m_y.shape[0], m_x.shape[0]).movedim(-3, -1)


# id(coordinate vector) -> (weak reference, its version, {(size, dtype): matrix}): the pixel and
# frame axes repeat every step. Keyed by the tensor itself, not its values: reading the values
# would wait for a GPU at every call.
_MATRIX_CACHE: dict[int, tuple] = {}


def _interp_matrix(coords: Tensor, size: int, dtype) -> Tensor:
    """(n, size) matrix of 1-D linear interpolation weights, align_corners=True, border clamp.

    Matrices for coordinate vectors that do not need a gradient are kept while the vector lives
    and is not changed in place."""
    return _cached(coords, (size, dtype), lambda: _build_interp_matrix(coords, size, dtype))


def _stacked_interp(coords: Tensor, sizes: Sequence[int], width: int, rows: int, dtype, repeat: int = 1) -> Tensor:
    """(len(sizes) * repeat, rows, width): the interpolation matrix of `coords` onto each of `sizes`
    knots (each `repeat` times in a row), zero-padded to `width` columns and `rows` rows (kept as
    `_interp_matrix` keeps its matrices)."""
    def build() -> Tensor:
        if _on_host(coords, dtype):
            m = np.zeros((len(sizes), rows, width), dtype=_HOST_DTYPES[dtype])
            for s, size in enumerate(sizes):
                m[s, :coords.shape[0], :size] = _host_interp_matrix(coords, size, dtype)
            return torch.from_numpy(np.repeat(m, repeat, axis=0))
        m = torch.zeros(len(sizes), rows, width, dtype=dtype, device=coords.device)
        for s, size in enumerate(sizes):
            m[s, :coords.shape[0], :size] = _build_interp_matrix(coords, size, dtype)
        return m[:, None].expand(len(sizes), repeat, rows, width).reshape(-1, rows, width)
    return _cached(coords, ("stacked", tuple(sizes), width, rows, dtype, repeat), build)


def _cached(coords: Tensor, key: tuple, build) -> Tensor:
    """build() kept under `key` while `coords` lives unchanged (built afresh where coords need a gradient)."""
    if coords.requires_grad:
        return build()
    entry = _MATRIX_CACHE.get(id(coords))
    if entry is None or entry[0]() is not coords or entry[1] != coords._version:
        ident = id(coords)
        entry = _MATRIX_CACHE[ident] = (weakref.ref(coords, lambda _ref, k=ident: _MATRIX_CACHE.pop(k, None)),
                                        coords._version, {})
    m = entry[2].get(key)
    if m is None:
        m = entry[2][key] = build()
    return m


# dtypes whose interpolation matrices for constant coordinates on a CPU are built in numpy (once, kept: a
# dozen tensor operations each, at every fit's first step, otherwise)
_HOST_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def _on_host(coords: Tensor, dtype) -> bool:
    return coords.device.type == "cpu" and not coords.requires_grad and dtype in _HOST_DTYPES


def _host_interp_matrix(coords: Tensor, size: int, dtype) -> np.ndarray:
    """`_build_interp_matrix`'s values, in the same arithmetic (each step rounded to `dtype`), in numpy."""
    real = _HOST_DTYPES[dtype]
    pos = np.clip((coords.numpy().astype(real) + real(1)) * real(0.5) * real(size - 1), real(0), real(size - 1))
    left = np.minimum(np.floor(pos), real(size - 2)).astype(np.int64)
    frac = pos - left.astype(real)
    m = np.zeros((coords.shape[0], size), dtype=real)
    rows = np.arange(coords.shape[0])
    m[rows, left] = real(1) - frac
    m[rows, left + 1] = frac
    return m


def _build_interp_matrix(coords: Tensor, size: int, dtype) -> Tensor:
    if _on_host(coords, dtype):
        return torch.from_numpy(_host_interp_matrix(coords, size, dtype))
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
    sources = dict(source.named_modules())
    done = set()
    with torch.no_grad():
        for name, field in target.named_modules():
            if not isinstance(field, PlaneField):
                continue
            other = sources.get(name)
            if not isinstance(other, PlaneField) or other.scale_count != field.scale_count \
                    or other.features != field.features:
                raise ValueError(f"plane field {name or 'field'}: its planes cannot become the target's")
            for p, q in zip(field.planes, other.planes, strict=True):
                q = q.to(p)
                p.copy_(q if q.shape == p.shape else
                        F.interpolate(q, size=p.shape[-2:], mode="bilinear", align_corners=True))
            done.update(f"{name}.{n}" if name else n for n, _ in field.named_parameters(recurse=False))
        for name, p in dst.items():
            if name in done:
                continue
            q = src[name].to(p)
            if q.shape != p.shape:
                raise ValueError(f"field parameter {name}: {tuple(q.shape)} cannot become {tuple(p.shape)}")
            p.copy_(q)
