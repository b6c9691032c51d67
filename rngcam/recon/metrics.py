"""Error measures against truth (PSNR, SSIM) and relative data residuals.

PSNR and SSIM use a data range of 1.0 (simulated truth is linear intensity in [0, 1]) and are
computed on the estimate as it is: no rescaling towards the truth.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


def psnr(estimate: Tensor, truth: Tensor, mask: Tensor | None = None, data_range: float = 1.0) -> float:
    """PSNR in dB over all elements (or the (H, W) `mask` region) of (C, T, H, W) videos."""
    total, count = 0.0, 0
    for e, t in zip(_frame_chunks(estimate), _frame_chunks(truth)):  # bounded temporaries at any size
        diff = (e.double() - t.double().to(e.device)) ** 2
        if mask is not None:
            m = mask.to(diff.device).expand_as(diff)
            total, count = total + float(diff[m].sum()), count + int(m.sum())
        else:
            total, count = total + float(diff.sum()), count + diff.numel()
    mse = total / count if count else float("nan")
    if mse == 0:
        return float("inf")
    return 10 * math.log10(data_range ** 2 / mse)


def _frame_chunks(video: Tensor, chunk: int = 16):
    """(C, T, H, W) -> views of `chunk` frames at a time."""
    return (video[:, i:i + chunk] for i in range(0, video.shape[1], chunk))


def _gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float64, device="cpu") -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def _valid_filter_matrix(g: Tensor, n: int) -> Tensor:
    """(n - len(g) + 1, n) matrix applying the 1-D filter g without padding."""
    m = torch.zeros(n - len(g) + 1, n, dtype=g.dtype, device=g.device)
    for i in range(m.shape[0]):
        m[i, i:i + len(g)] = g
    return m


def ssim(estimate: Tensor, truth: Tensor, mask: Tensor | None = None, data_range: float = 1.0) -> float:
    """Mean SSIM (Wang et al. 2004, Gaussian 11x11, sigma 1.5) over frames and channels.

    Each frame of each channel is one 2-D image; windows shrink for images under 11 px.
    """
    total, count = 0.0, 0
    for e, t in zip(_frame_chunks(estimate), _frame_chunks(truth)):  # bounded temporaries at any size
        s_sum, n = _ssim_sums(e, t, mask, data_range)
        total, count = total + s_sum, count + n
    return total / count if count else float("nan")


def _ssim_sums(estimate: Tensor, truth: Tensor, mask: Tensor | None, data_range: float) -> tuple[float, int]:
    """(sum of the SSIM map, its number of values) for a chunk of frames."""
    # float32 filtering: float64 conv2d is ~20x slower on CPU and SSIM needs no more precision.
    x = estimate.float().reshape(-1, 1, *estimate.shape[-2:])
    y = truth.float().to(x.device).reshape(-1, 1, *truth.shape[-2:])
    size = min(11, x.shape[-1], x.shape[-2])
    size -= (size + 1) % 2  # odd
    g = _gaussian_window(size, 1.5, x.dtype, x.device)
    if mask is not None:
        crop = size // 2
        mask = mask[crop:mask.shape[-2] - crop, crop:mask.shape[-1] - crop]

    gh, gw = _valid_filter_matrix(g, x.shape[-2]), _valid_filter_matrix(g, x.shape[-1])

    def blur(z):  # separable 'valid' filtering as two matrix products (border windows left out, as in scikit-image)
        return gh @ z @ gw.T

    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    if mask is not None:
        m = mask.to(s.device).expand_as(s)
        return float(s[m].sum()), int(m.sum())
    return float(s.sum()), s.numel()


def video_metrics(estimate: Tensor, truth: Tensor, intermediate: np.ndarray,
                  mask: Tensor | None = None) -> dict[str, float]:
    """PSNR/SSIM over all frames and over the intermediate frames (away from GS key frames)."""
    out = {"psnr_db": psnr(estimate, truth, mask), "ssim": ssim(estimate, truth, mask)}
    if len(intermediate):
        idx = torch.as_tensor(intermediate, device=estimate.device)
        e, t = estimate.index_select(1, idx), truth.index_select(1, idx.to(truth.device))
        out["psnr_intermediate_db"] = psnr(e, t, mask)
        out["ssim_intermediate"] = ssim(e, t, mask)
    return out


def relative_residual(pred: Tensor, meas: Tensor) -> float:
    """||pred - meas|| / ||meas|| (0/0 -> 0, x/0 -> inf)."""
    num = float(torch.linalg.vector_norm((pred - meas).double()))
    den = float(torch.linalg.vector_norm(meas.double()))
    if den == 0:
        return 0.0 if num == 0 else float("inf")
    return num / den


def psnr_np(estimate: np.ndarray, truth: np.ndarray) -> float:
    return psnr(torch.from_numpy(np.asarray(estimate)), torch.from_numpy(np.asarray(truth)))


def error_visibility(problem, estimate: Tensor, frame_chunk: int = 16) -> dict[str, float]:
    """What each measurement sees of an estimate's error, in units of its noise: per sensor
    ("rs", "gs"), ||A (estimate - truth)|| / ||A truth - b|| (needs the truth; gains taken as 1).

    Below 1 the error hides under the measurement's noise: no closer fit to the data can find it,
    only a better prior. inf when a measurement has no noise but sees the error; nan without truth.
    The RS operator takes `frame_chunk` frames at a time, so memory does not grow with K beyond
    the error video itself.
    """
    sensors = {"rs": (problem.b_rs, lambda x: problem.rs_op().A(x, frame_chunk=frame_chunk)),
               "gs": (problem.b_gs, lambda x: problem.gs_op().A(x))}
    sensors = {name: pair for name, pair in sensors.items() if pair[0] is not None}
    if problem.truth is None:
        return {name: math.nan for name in sensors}
    truth = problem.truth
    error = estimate.to(truth.device, truth.dtype) - truth
    out = {}
    for name, (meas, forward) in sensors.items():
        signal = float(torch.linalg.vector_norm(forward(error).double()))
        noise = float(torch.linalg.vector_norm((forward(truth) - meas).double()))
        out[name] = signal / noise if noise > 0 else (0.0 if signal == 0 else math.inf)
    return out
