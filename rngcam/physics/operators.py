"""Linear forward operators with `A` and `A_adjoint` (modelled on deepinv's LinearPhysics).

Shapes (docs/design.md): video (C, T, H, W); one measurement (C, H, W); a GS stack (C, G, H, W).
Operators work in float32 or float64, on any device, batched over colour channels. A stacked
operator returns a tuple of measurements; `inner` and `norm_sq` handle tensors and tuples.
"""

from __future__ import annotations

import copy
import math
import threading

import torch
from torch import Tensor

Measurement = Tensor | tuple[Tensor, ...]


def inner(a: Measurement, b: Measurement) -> Tensor:
    """Real inner product <a, b> of tensors or tuples of tensors."""
    if isinstance(a, tuple):
        zero = torch.zeros((), dtype=a[0].dtype, device=a[0].device)
        return sum((inner(x, y) for x, y in zip(a, b, strict=True)), zero)
    return (a * b).sum()


def norm_sq(a: Measurement) -> Tensor:
    return inner(a, a)


def _next_fast_len(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n (sizes pocketfft/cuFFT handle fastest)."""
    best = 2 ** math.ceil(math.log2(max(n, 1)))
    p5 = 1
    while p5 < 2 * n:
        p35 = p5
        while p35 < 2 * n:
            p2 = p35
            while p2 < n:
                p2 *= 2
            best = min(best, p2)
            p35 *= 3
        p5 *= 5
    return best


def compute_dtype(stored, wanted=None):
    """The dtype to compute in for data stored as `stored`: `wanted`, else `stored`, except that
    half precision (a storage format here, never arithmetic) computes in float32."""
    if wanted is not None:
        return wanted
    return torch.float32 if stored in (torch.float16, torch.bfloat16) else stored


class LinearOperator:
    """Base class: subclasses implement A and A_adjoint; `domain_shape` is the input shape."""

    domain_shape: tuple[int, ...]

    def A(self, x: Tensor) -> Measurement:  # noqa: N802 (deepinv naming)
        raise NotImplementedError

    def A_adjoint(self, y: Measurement) -> Tensor:  # noqa: N802
        raise NotImplementedError

    def A_normal(self, x: Tensor) -> Tensor:  # noqa: N802
        return self.A_adjoint(self.A(x))

    def norm(self, iters: int = 50, dtype=torch.float64, device=None, seed: int = 0,
             tol: float = 1e-7) -> float:
        """Operator 2-norm ||A|| by power iteration on A^T A (deterministic start)."""
        gen = torch.Generator(device="cpu").manual_seed(seed)
        x = torch.randn(self.domain_shape, generator=gen, dtype=dtype).to(device or "cpu")
        x = x / x.norm()
        lam = 0.0
        for _ in range(iters):
            z = self.A_normal(x)
            new = float(inner(x, z))
            nz = float(z.norm())
            if nz == 0.0:
                return 0.0
            x = z / nz
            if abs(new - lam) <= tol * max(abs(new), 1e-30):
                lam = new
                break
            lam = new
        return math.sqrt(max(lam, 0.0))


class PSFConvolution(LinearOperator):
    """Linear (zero-padded, not circular) 'same' convolution of (C, ..., H, W) with a PSF.

    The PSF has shape (C, Hp, Wp) or (1, Hp, Wp) (shared by all channels). Output pixel i sees
    input pixel i through the PSF's pixel (Hp//2, Wp//2): a delta there is the identity. The
    transfer function is computed once per dtype/device with real FFTs.
    """

    def __init__(self, psf: Tensor, image_shape: tuple[int, int], batch_shape: tuple[int, ...] = (),
                 channels: int | None = None):
        psf = torch.as_tensor(psf)
        if psf.ndim == 2:
            psf = psf[None]
        if psf.ndim != 3:
            raise ValueError(f"PSF must be (C, Hp, Wp), got shape {tuple(psf.shape)}")
        if not torch.isfinite(psf).all():
            raise ValueError("PSF contains NaN or Inf")
        self.psf = psf
        self.image_shape = (int(image_shape[0]), int(image_shape[1]))
        h, w = self.image_shape
        hp, wp = psf.shape[-2:]
        self.fft_shape = (_next_fast_len(h + hp - 1), _next_fast_len(w + wp - 1))
        self.offset = (hp // 2, wp // 2)
        channels = psf.shape[0] if channels is None else int(channels)
        if psf.shape[0] not in (1, channels):
            raise ValueError(f"a {psf.shape[0]}-channel PSF cannot act on {channels} channels")
        self.domain_shape = (channels, *batch_shape, h, w)
        self._cache: dict = {}

    def transfer(self, dtype, device) -> Tensor:
        key = (dtype, str(device))
        if key not in self._cache:
            p = self.psf.to(device=device, dtype=dtype)
            self._cache[key] = torch.fft.rfft2(p, s=self.fft_shape)
        return self._cache[key]

    def _broadcast(self, tf: Tensor, ndim: int) -> Tensor:
        return tf.reshape(tf.shape[0], *([1] * (ndim - 3)), *tf.shape[-2:])

    def A(self, x: Tensor) -> Tensor:  # noqa: N802
        h, w = self.image_shape
        tf = self._broadcast(self.transfer(x.dtype, x.device), x.ndim)
        z = torch.fft.irfft2(torch.fft.rfft2(x, s=self.fft_shape) * tf, s=self.fft_shape)
        oy, ox = self.offset
        return z[..., oy:oy + h, ox:ox + w]

    def A_adjoint(self, y: Tensor) -> Tensor:  # noqa: N802
        # Correlation with the PSF: embed y at the crop offset, multiply by conj(H), keep [0:h, 0:w].
        # The FFT size >= h + hp - 1 guarantees no circular wrap-around reaches the kept region.
        h, w = self.image_shape
        oy, ox = self.offset
        fh, fw = self.fft_shape
        tf = self._broadcast(self.transfer(y.dtype, y.device), y.ndim)
        yp = torch.nn.functional.pad(y, (ox, fw - w - ox, oy, fh - h - oy))
        z = torch.fft.irfft2(torch.fft.rfft2(yp) * tf.conj(), s=self.fft_shape)
        return z[..., :h, :w]


SCRATCH_PER_NAME = 2  # kept scratch buffers per name and thread (RollingShutter._buffer)
_SCRATCH = threading.local()


def _scratch() -> dict:
    """This thread's kept scratch buffers, by (name, shape, dtype, device, zeroed, tag)."""
    if not hasattr(_SCRATCH, "pool"):
        _SCRATCH.pool = {}
    return _SCRATCH.pool


def drop_scratch() -> None:
    """Let go of this thread's kept scratch buffers (a run's end: the next calls make new ones)."""
    _scratch().clear()


class RollingShutter(LinearOperator):
    """RS measurement: convolve each frame with the PSF, weight row i of frame k by W[i, k], sum over k.

    v (C, K, H, W) -> b (C, H, W). W is (H, K) from RollingShutterTiming.weights.

    Frame k only reaches the few rows whose exposure overlaps it (W is banded), so neither
    direction inverts a whole padded spectrum along y per frame: the forward evaluates only
    those rows of the inverse DFT along y (a small matrix product), and the adjoint builds each
    frame's spectrum from those rows of the x-transformed measurement. Frames go through the
    FFTs a chunk at a time into buffers that are reused across calls (outside autograd), so the
    cost is one batched rfft2 (forward) or irfft2 (adjoint) without allocation churn.
    """

    # Complex spectrum per chunk of frames: small enough that the FFT library's own scratch stays
    # under glibc's mmap threshold (32 MiB at most), so it is reused instead of mapped and faulted in.
    CHUNK_BYTES = 16 * 2**20

    def __init__(self, psf: Tensor, weights: Tensor, width: int, channels: int | None = None):
        self.weights = torch.as_tensor(weights)
        rows, k = self.weights.shape
        self.conv = PSFConvolution(psf, (rows, width), batch_shape=(k,), channels=channels)
        self.domain_shape = self.conv.domain_shape
        self._band_cache: dict = {}
        self._row_dft_cache: dict = {}  # independent of the weights: shared by with_weights' copies

    def with_weights(self, weights: Tensor) -> RollingShutter:
        """The same PSF and shape with other row weights (H, K): the PSF's transfer is shared."""
        out = copy.copy(self)
        out.weights, out._band_cache = torch.as_tensor(weights), {}
        return out

    def _w(self, like: Tensor) -> Tensor:
        return self.weights.to(dtype=like.dtype, device=like.device)

    def _w_kh1(self, like: Tensor) -> Tensor:
        """Weights as (K, H, 1) for broadcasting against (C, K, H, W)."""
        return self._w(like).T[:, :, None]

    def _band(self, dtype, device) -> tuple[Tensor, Tensor, Tensor]:
        """Per frame k the rows it reaches (any of them, in order; padded with weight 0): row indices (K, n)
        and the DFT matrices of those rows,
        forward (K, n, fh) = W e^{+2 pi i f (r + oy) / fh} / fh and adjoint (K, fh, n) = W e^{-...}."""
        key = (dtype, str(device))
        if key not in self._band_cache:
            w = self.weights.detach().to(torch.float64).cpu()
            h, k = w.shape
            nz = w.T != 0  # (K, H)
            count = nz.sum(dim=1)
            n = max(int(count.max()) if k else 0, 1)
            # Each frame's reached rows in order, not necessarily adjacent (a dual readout reaches two
            # groups at once): sort the rows it reaches before the others, keep the first n.
            r = torch.arange(h)
            order = torch.where(nz, r[None], r[None] + h)
            rows = order.sort(dim=1).values[:, :n]
            inside = torch.arange(rows.shape[1])[None] < count[:, None]
            rows = torch.where(inside, rows, rows.clamp_max(h - 1))
            wk = torch.where(inside, w.T.gather(1, rows), torch.zeros(()))  # (K, n)
            fh = self.conv.fft_shape[0]
            phase = 2 * math.pi * torch.arange(fh, dtype=torch.float64)[None, None] * (
                rows + self.conv.offset[0])[..., None] / fh  # (K, n, fh)
            fwd = wk[..., None] * torch.polar(torch.ones_like(phase), phase) / fh
            adj = (wk[..., None] * torch.polar(torch.ones_like(phase), -phase)).transpose(1, 2)
            cdt = (torch.ones((), dtype=dtype) * 1j).dtype
            self._band_cache[key] = (rows.to(device), fwd.to(device=device, dtype=cdt).contiguous(),
                                     adj.to(device=device, dtype=cdt).contiguous())
        return self._band_cache[key]

    def _row_dft(self, dtype, device) -> Tensor:
        """(H, fh) rows of the inverse DFT along y, e^{+2 pi i f (r + oy) / fh} / fh, for every grid row r."""
        key = (dtype, str(device))
        if key not in self._row_dft_cache:
            fh = self.conv.fft_shape[0]
            rows = torch.arange(self.weights.shape[0], dtype=torch.float64) + self.conv.offset[0]
            phase = (2 * math.pi / fh) * torch.outer(rows, torch.arange(fh, dtype=torch.float64))
            self._row_dft_cache[key] = (torch.polar(torch.ones_like(phase), phase) / fh).to(device, dtype)
        return self._row_dft_cache[key]

    def frames_per_chunk(self, channels: int, frame_chunk: int | None = None) -> int:
        """Frames that go through the FFTs at a time: `frame_chunk`, else as many as fit CHUNK_BYTES."""
        if frame_chunk is not None:
            return max(1, int(frame_chunk))
        fh, fw = self.conv.fft_shape
        return max(1, self.CHUNK_BYTES // (channels * fh * (fw // 2 + 1) * 8))

    def _buffer(self, name: str, shape, dtype, device, reuse: bool, zero: bool = False,
                tag: tuple = ()) -> Tensor | None:
        """A scratch tensor kept across calls (None under autograd: out= is not differentiable).
        Kept per thread, not per operator: a run builds many operators (every level, every
        ensemble member, the start floor's), and each kept four 16 MiB buffers of its own. `tag`
        tells apart buffers whose contents matter between calls (the zero padding of one image size)."""
        if not reuse:
            return None
        pool = _scratch()
        key = (name, tuple(shape), dtype, str(device), zero, tag)
        buf = pool.pop(key, None)
        if buf is None:
            make = torch.zeros if zero else torch.empty
            buf = make(shape, dtype=dtype, device=device)
        pool[key] = buf  # the most recently used last
        same = [k for k in pool if k[0] == name]
        for k in same[:-SCRATCH_PER_NAME]:  # a few shapes per name (levels alternate with the floor's grid)
            del pool[k]
        return buf

    def A(self, v: Tensor, frame_chunk: int | None = None, dtype=None) -> Tensor:  # noqa: N802
        """With `frame_chunk`, that many frames go through the FFTs at a time (default: as many
        as fit CHUNK_BYTES); the result does not depend on it. `dtype`: what to compute in
        (default: v's; float32 for a half-precision v): each chunk is cast on its way in, so a
        video kept in half precision, or measured in float64, needs no cast copy of itself."""
        conv = self.conv
        h, w = conv.image_shape
        ox = conv.offset[1]
        fh, fw = conv.fft_shape
        c, k = v.shape[0], v.shape[1]
        dt = compute_dtype(v.dtype, dtype)
        tf = conv.transfer(dt, v.device)[:, None]  # (C|1, 1, fh, fw')
        rows_k, fwd, _ = self._band(dt, v.device)
        n = rows_k.shape[1]
        reuse = not (torch.is_grad_enabled() and v.requires_grad)
        step = self.frames_per_chunk(c, frame_chunk)
        rows = torch.zeros((c, h, fw // 2 + 1), dtype=fwd.dtype, device=v.device)
        for start in range(0, k, step):
            m = min(step, k - start)
            if reuse:  # zero-padded frames in a kept buffer: only the top-left block is ever written
                padded = self._buffer("padded", (c, step, fh, fw), dt, v.device, reuse, zero=True, tag=(h, w))[:, :m]
                padded[..., :h, :w] = v[:, start:start + m]
                buf = self._buffer("spec", (c, step, fh, fw // 2 + 1), fwd.dtype, v.device, reuse)[:, :m]
                spec = torch.fft.rfft2(padded, out=buf).mul_(tf)
            else:
                spec = torch.fft.rfft2(v[:, start:start + m].to(dt), s=conv.fft_shape) * tf
            # Only the rows each frame reaches, of the inverse DFT along y, weighted: (C, m, n, fw').
            part = torch.matmul(fwd[start:start + m], spec)
            idx = rows_k[start:start + m].reshape(-1)
            part = part.reshape(c, m * n, -1)
            rows = rows.index_add_(1, idx, part) if reuse else rows.index_add(1, idx, part)
        return torch.fft.irfft(rows, n=fw, dim=-1)[..., ox:ox + w]

    def A_adjoint(self, b: Tensor, frame_chunk: int | None = None, out: Tensor | None = None) -> Tensor:  # noqa: N802
        """`out`: a (C, K, H, W) tensor to write the video into (of any floating dtype: each chunk
        is cast on its way out), instead of a new one in b's dtype."""
        conv = self.conv
        h, w = conv.image_shape
        ox = conv.offset[1]
        fh, fw = conv.fft_shape
        c, k = b.shape[0], self.weights.shape[1]
        tfc = conv.transfer(b.dtype, b.device).conj()[:, None]
        rows_k, _, adj = self._band(b.dtype, b.device)
        reuse = not (torch.is_grad_enabled() and b.requires_grad)
        # The row weights commute with the transform along x: transform the measurement once.
        bx = torch.fft.rfft(torch.nn.functional.pad(b, (ox, fw - w - ox)), dim=-1)  # (C, H, fw')
        parts = []  # under autograd: the chunks, concatenated at the end
        if reuse and out is None:
            out = torch.empty((c, k, h, w), dtype=b.dtype, device=b.device)
        step = self.frames_per_chunk(c, frame_chunk)
        for start in range(0, k, step):
            m = min(step, k - start)
            sel = bx[:, rows_k[start:start + m]]  # (C, m, n, fw')
            if reuse:
                buf = self._buffer("spec", (c, step, fh, fw // 2 + 1), adj.dtype, b.device, reuse)[:, :m]
                spec = torch.matmul(adj[start:start + m], sel, out=buf).mul_(tfc)
                col = self._buffer("spec2", (c, step, fh, fw // 2 + 1), adj.dtype, b.device, reuse)[:, :m]
                col = torch.fft.ifft(spec, dim=-2, out=col)[..., :h, :]
                img = self._buffer("image", (c, step, h, fw), b.dtype, b.device, reuse)[:, :m]
                out[:, start:start + m] = torch.fft.irfft(col, n=fw, dim=-1, out=img)[..., :w]
            else:
                spec = torch.matmul(adj[start:start + m], sel) * tfc
                col = torch.fft.ifft(spec, dim=-2)[..., :h, :]
                parts.append(torch.fft.irfft(col, n=fw, dim=-1)[..., :w])
        if reuse:
            return out
        return torch.cat(parts, dim=1) if out is None else out.copy_(torch.cat(parts, dim=1))

    def A_rows(self, v_frames: Tensor, rows: Tensor, frames: Tensor,  # noqa: N802
               weights: Tensor | None = None) -> Tensor:
        """Sensor rows `rows` (R,) as seen from frames `frames` (F,) only: v_frames (C, F, H, W)
        -> (C, R, W). Summed over frame subsets that partition the video it gives A(v)[:, rows];
        only those rows go through the inverse FFT along x (a fit's step samples a few rows).
        `weights` (R, F): these rows' weights on these frames instead of the operator's (a fit
        that learns the line time passes them, with their gradient)."""
        conv = self.conv
        h, w = conv.image_shape
        ox = conv.offset[1]
        fh, fw = conv.fft_shape
        c, n = v_frames.shape[0], v_frames.shape[1]
        tf = conv._broadcast(conv.transfer(v_frames.dtype, v_frames.device), v_frames.ndim)
        rows = rows.to(v_frames.device)
        spec = torch.fft.rfft2(v_frames, s=conv.fft_shape) * tf  # (C, F, fh, fw')
        # Only rows `rows` of the inverse DFT along y, weighted per frame and summed over frames:
        # one (R, F fh) x (F fh, fw') product instead of a full inverse FFT per frame and a selection.
        if weights is None:
            weights = self._w(v_frames)[rows][:, frames.to(v_frames.device)]
        weights = weights.to(v_frames).T  # (F, R)
        dft = self._row_dft(spec.dtype, spec.device).index_select(0, rows)  # (R, fh)
        band = (weights.T[:, :, None].to(spec.dtype) * dft[:, None, :]).reshape(len(rows), n * fh)
        summed = torch.matmul(band, spec.reshape(c, n * fh, -1))  # (C, R, fw // 2 + 1)
        return torch.fft.irfft(summed, n=fw, dim=-1)[..., ox:ox + w]

    def A_rows_adjoint(self, b_rows: Tensor, rows: Tensor, frames: Tensor,  # noqa: N802
                       weights: Tensor | None = None) -> Tensor:
        """Adjoint of A_rows (with the same `weights`, if any): (C, R, W) -> (C, F, H, W)."""
        c, _, w = b_rows.shape
        h = self.conv.image_shape[0]
        if weights is None:
            weights = self._w(b_rows)[rows.to(b_rows.device)][:, frames.to(b_rows.device)]
        weights = weights.to(b_rows).T  # (F, R)
        full = torch.zeros(c, len(frames), h, w, dtype=b_rows.dtype, device=b_rows.device)
        full[:, :, rows.to(b_rows.device)] = b_rows[:, None] * weights[None, :, :, None]
        return self.conv.A_adjoint(full)


class GlobalShutter(LinearOperator):
    """GS measurement: frame g is the weighted sum of video frames, sum_k W[g, k] v_k.

    v (C, K, H, W) -> (C, G, H, W). W is (G, K) from GlobalShutterTiming.weights.
    """

    def __init__(self, weights: Tensor, channels: int, image_shape: tuple[int, int]):
        self.weights = torch.as_tensor(weights)
        self.domain_shape = (channels, self.weights.shape[1], *image_shape)

    def _w(self, like: Tensor) -> Tensor:
        return self.weights.to(dtype=like.dtype, device=like.device)

    def A(self, v: Tensor) -> Tensor:  # noqa: N802
        return torch.einsum("ckhw,gk->cghw", v, self._w(v))

    def A_adjoint(self, b: Tensor) -> Tensor:  # noqa: N802
        return torch.einsum("cghw,gk->ckhw", b, self._w(b))

    def A_frames(self, v_frames: Tensor, windows: Tensor, frames: Tensor) -> Tensor:  # noqa: N802
        """GS frames `windows` (n,) as seen from video frames `frames` (F,) only:
        v_frames (C, F, H, W) -> (C, n, H, W) (exact when `frames` hold all those exposures touch)."""
        w = self._w(v_frames)[windows.to(v_frames.device)][:, frames.to(v_frames.device)]
        return torch.einsum("cfhw,gf->cghw", v_frames, w)

    def A_frames_adjoint(self, b: Tensor, windows: Tensor, frames: Tensor) -> Tensor:  # noqa: N802
        """Adjoint of A_frames: (C, n, H, W) -> (C, F, H, W)."""
        w = self._w(b)[windows.to(b.device)][:, frames.to(b.device)]
        return torch.einsum("cghw,gf->cfhw", b, w)

    def norm(self, *args, **kwargs) -> float:
        """Exact: A^T A acts on each pixel as W^T W, so ||A|| = sqrt(largest eigenvalue of W W^T)."""
        w = self.weights.double().cpu()
        if w.numel() == 0:
            return 0.0
        return float(torch.linalg.eigvalsh(w @ w.T)[-1].clamp_min(0).sqrt())


class Stacked(LinearOperator):
    """[sqrt(psi) A_R; A_G]: so ||Stacked v - (sqrt(psi) b_R, b_G)||^2 = psi||A_R v - b_R||^2 + ||A_G v - b_G||^2."""

    def __init__(self, rs: RollingShutter, gs: GlobalShutter, psi: float = 1.0):
        if not (math.isfinite(psi) and psi >= 0):
            raise ValueError(f"psi must be finite and >= 0, got {psi!r}")
        if tuple(rs.domain_shape) != tuple(gs.domain_shape):
            raise ValueError(f"RS and GS operators disagree on the video shape: "
                             f"{rs.domain_shape} vs {gs.domain_shape}")
        self.rs, self.gs, self.psi = rs, gs, float(psi)
        self.domain_shape = rs.domain_shape

    def A(self, v: Tensor) -> tuple[Tensor, Tensor]:  # noqa: N802
        return math.sqrt(self.psi) * self.rs.A(v), self.gs.A(v)

    def A_adjoint(self, y: tuple[Tensor, Tensor]) -> Tensor:  # noqa: N802
        return math.sqrt(self.psi) * self.rs.A_adjoint(y[0]) + self.gs.A_adjoint(y[1])


class Transposed(LinearOperator):
    """`op` acting on images with their last two axes swapped: A(x) = T op.A(T x), T the transpose
    of (..., H, W). T is a permutation, its own inverse and adjoint, so A^T = T op.A^T T exactly.
    A readout along columns is a top-down readout of the transposed sensor (physics.timing)."""

    def __init__(self, op: LinearOperator):
        self.op = op
        *lead, h, w = op.domain_shape
        self.domain_shape = (*lead, w, h)

    def A(self, x: Tensor) -> Tensor:  # noqa: N802
        return self.op.A(x.transpose(-1, -2)).transpose(-1, -2)

    def A_adjoint(self, y: Tensor) -> Tensor:  # noqa: N802
        return self.op.A_adjoint(y.transpose(-1, -2)).transpose(-1, -2)


def rolling_shutter_for(psf: Tensor, weights: Tensor, image_shape: tuple[int, int], channels: int | None = None,
                        transposed: bool = False) -> LinearOperator:
    """The RS operator on sensor-oriented video (C, K, H, W) = image_shape (H, W): RollingShutter, or
    for a timing whose rows are the sensor's columns (`transposed`, RollingShutterTiming.transposed)
    the same along columns, with the weights (W, K) and the PSF transposed."""
    h, w = image_shape
    psf = torch.as_tensor(psf)
    if not transposed:
        return RollingShutter(psf, weights, width=w, channels=channels)
    return Transposed(RollingShutter(psf.transpose(-1, -2), weights, width=h, channels=channels))
