"""2-D deconvolution of one diffuser (RS) image of a static scene: Wiener, then FISTA-TV.

Model: b = A x + noise with A = rngcam.physics.operators.PSFConvolution (linear, zero-padded),
x >= 0 the scene on the RS grid (C, H, W). The TV solve minimises

    F(x) = 1/2 ||A x - b||^2 + tau * TV(x),   x >= 0,

TV the anisotropic 2-D total variation of rngcam.physics.tv_prox applied to x as a (C, T=1, H, W)
video, by monotone FISTA (Beck & Teboulle 2009, MFISTA): the accepted iterate is the better of
the new prox point and the previous iterate, so F never increases even with the fast Haar
approximation of the TV prox. The step is 1/L with L = max |H(f)|^2 on the padded FFT grid,
an upper bound of ||A||^2. tau is given relative to max |b| (`tau_rel`).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from rngcam.cpu import torch_threads
from rngcam.errors import RngcamError
from rngcam.physics.operators import PSFConvolution
from rngcam.physics.tv_prox import prox_tv_nonneg, tv3

SMALL_PIXELS = 512 * 512  # below this per channel, torch's intra-op threads only cost time


@contextlib.contextmanager
def few_threads(pixels: int):
    """Run small FFT work on one torch thread (restored afterwards). On a busy 2-core machine a
    (3, 128, 128) rfft2 took 20 ms with two intra-op threads and 0.3 ms with one."""
    with torch_threads(1 if pixels < SMALL_PIXELS else torch.get_num_threads()):
        yield


@dataclass
class DeconvResult:
    """image: (C, H, W) float64 >= 0. objective[k] = F after iteration k (objective[0]: start)."""

    image: np.ndarray
    objective: list[float] = field(default_factory=list)
    tau: float = 0.0
    seconds: float = 0.0


def _as_tensor(b: np.ndarray, psf: np.ndarray) -> tuple[torch.Tensor, PSFConvolution]:
    b = np.asarray(b, dtype=np.float64)
    if b.ndim == 2:
        b = b[None]
    if b.ndim != 3:
        raise RngcamError(f"deconvolution needs a (C, H, W) image, got shape {b.shape}")
    if not np.all(np.isfinite(b)):
        raise RngcamError("deconvolution input contains NaN or Inf")
    psf = np.asarray(psf, dtype=np.float64)
    psf = psf[None] if psf.ndim == 2 else psf
    if psf.shape[0] not in (1, b.shape[0]):
        raise RngcamError(f"a {psf.shape[0]}-channel PSF cannot deconvolve a {b.shape[0]}-channel image")
    op = PSFConvolution(torch.from_numpy(psf), b.shape[-2:], batch_shape=(1,), channels=b.shape[0])
    return torch.from_numpy(b)[:, None], op


def wiener(b: np.ndarray, psf: np.ndarray, nsr: float = 1e-3) -> np.ndarray:
    """Wiener estimate conj(H) B / (|H|^2 + nsr max|H|^2) on the operator's padded FFT grid
    (the measurement embedded where A puts it, the result cropped like A's domain), >= 0."""
    bt, op = _as_tensor(b, psf)
    h, w = op.image_shape
    oy, ox = op.offset
    fh, fw = op.fft_shape
    tf = op.transfer(torch.float64, "cpu")[:, None]
    padded = torch.nn.functional.pad(bt, (ox, fw - w - ox, oy, fh - h - oy))
    reg = nsr * float(tf.abs().max()) ** 2
    x = torch.fft.irfft2(torch.fft.rfft2(padded) * tf.conj() / (tf.abs() ** 2 + reg), s=op.fft_shape)
    return x[:, 0, :h, :w].clamp(min=0).numpy()


def deconvolve(b: np.ndarray, psf: np.ndarray, tau_rel: float = 1e-3, iters: int = 100,
               wiener_nsr: float = 1e-3, prox: str = "haar") -> DeconvResult:
    """Wiener start, then `iters` MFISTA iterations on F (module docstring). Returns the scene
    estimate and the objective after each iteration (non-increasing)."""
    with few_threads(int(np.prod(np.shape(b)[-2:]))):
        return _deconvolve(b, psf, tau_rel, iters, wiener_nsr, prox)


def _deconvolve(b, psf, tau_rel, iters, wiener_nsr, prox) -> DeconvResult:
    t0 = time.perf_counter()
    if not (math.isfinite(tau_rel) and tau_rel >= 0):
        raise RngcamError(f"tau_rel must be finite and >= 0, got {tau_rel}")
    bt, op = _as_tensor(b, psf)
    lipschitz = float(op.transfer(torch.float64, "cpu").abs().max()) ** 2
    if lipschitz <= 0:
        raise RngcamError("the PSF has no signal: cannot deconvolve")
    tau = tau_rel * float(bt.abs().max())
    step = 1.0 / lipschitz

    def objective(x: torch.Tensor, ax: torch.Tensor) -> float:
        r = ax - bt
        return 0.5 * float((r * r).sum()) + tau * float(tv3(x, 0.0))

    # A is linear, so A y is combined from A x, A z and A x_prev: one A and one A^T per iteration.
    x = torch.from_numpy(wiener(b, psf, wiener_nsr))[:, None].to(torch.float64)
    ax = op.A(x)
    f_x = objective(x, ax)
    history = [f_x]
    y, ay, t = x.clone(), ax.clone(), 1.0
    for _ in range(iters):
        z = prox_tv_nonneg(y - step * op.A_adjoint(ay - bt), tau * step, 0.0, method=prox)
        az = op.A(z)
        f_z = objective(z, az)
        t_next = (1 + math.sqrt(1 + 4 * t * t)) / 2
        x_prev, ax_prev = x, ax
        if f_z <= f_x:
            x, ax, f_x = z, az, f_z
        c_z, c_prev = t / t_next, (t - 1) / t_next
        y = x + c_z * (z - x) + c_prev * (x - x_prev)
        ay = ax + c_z * (az - ax) + c_prev * (ax - ax_prev)
        t = t_next
        history.append(f_x)
    image = x[:, 0].numpy()
    if not np.all(np.isfinite(image)):
        raise RngcamError("deconvolution diverged (non-finite result)")
    return DeconvResult(image=image, objective=history, tau=tau, seconds=time.perf_counter() - t0)
