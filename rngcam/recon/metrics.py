"""Error measures against truth (PSNR, SSIM) and relative data residuals.

PSNR and SSIM use a data range of 1.0 (simulated truth is linear intensity in [0, 1]) and are
computed on the estimate as it is: no rescaling towards the truth.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rngcam.errors import RngcamError
from rngcam.recon.noise import image_noise_std, row_noise_std
from rngcam.untrusted import load_yaml


def psnr(estimate: Tensor, truth: Tensor, mask: Tensor | None = None, data_range: float = 1.0,
         frames: np.ndarray | None = None) -> float:
    """PSNR in dB over all elements (or the (H, W) `mask` region) of (C, T, H, W) videos, over
    `frames` (default: all)."""
    total, count = 0.0, 0
    for e, t in _frame_chunks(estimate, truth, frames):  # bounded temporaries at any size
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


# The bytes of one float64 chunk a metric works on: a large grid's chunk (several such temporaries at
# once) would otherwise raise the heap by hundreds of MB at every log row (bench/convergence.md, seventh round)
CHUNK_BYTES = 4 * 2**20


def metric_chunk_frames(video: Tensor, value_bytes: int = 8) -> int:
    """Frames of a ([C,] K, H, W) video whose values, `value_bytes` each (float64), fill CHUNK_BYTES
    (at least one)."""
    per_frame = value_bytes * math.prod(video.shape[:-3]) * video.shape[-2] * video.shape[-1]
    return max(1, CHUNK_BYTES // max(1, per_frame))


def _frame_chunks(a: Tensor, b: Tensor, frames: np.ndarray | None = None, chunk: int | None = None):
    """Pairs of (C, n, H, W) chunks of two videos, `chunk` of `frames` (default all) at a time
    (default: `metric_chunk_frames`): views where the frames are consecutive, small copies otherwise."""
    chunk = chunk or metric_chunk_frames(a)
    if frames is None:
        for i in range(0, a.shape[1], chunk):
            yield a[:, i:i + chunk], b[:, i:i + chunk]
        return
    idx = torch.as_tensor(np.asarray(frames), dtype=torch.long)
    for i in range(0, len(idx), chunk):
        j = idx[i:i + chunk]
        yield a.index_select(1, j.to(a.device)), b.index_select(1, j.to(b.device))


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


def ssim(estimate: Tensor, truth: Tensor, mask: Tensor | None = None, data_range: float = 1.0,
         frames: np.ndarray | None = None) -> float:
    """Mean SSIM (Wang et al. 2004, Gaussian 11x11, sigma 1.5) over `frames` (default: all) and
    channels.

    Each frame of each channel is one 2-D image; windows shrink for images under 11 px.
    """
    sums, counts = ssim_frame_sums(estimate, truth, mask, data_range, frames)
    return float(sums.sum() / counts.sum()) if counts.sum() else float("nan")


def ssim_frame_sums(estimate: Tensor, truth: Tensor, mask: Tensor | None = None, data_range: float = 1.0,
                    frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of `frames` (default: all), the sum of the SSIM map over channels and its number of
    values, so several frame sets' means come from one filtering pass (the costly part; bench/large_grids.md)."""
    sums, counts = [], []
    for e, t in _frame_chunks(estimate, truth, frames):  # bounded temporaries at any size
        s_sum, n = _ssim_sums(e, t, mask, data_range)
        sums.append(s_sum)
        counts.append(n)
    if not sums:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(sums), np.concatenate(counts)


def _ssim_sums(estimate: Tensor, truth: Tensor, mask: Tensor | None,
               data_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of a (C, k, H, W) chunk: the SSIM map's sum over channels and its number of values."""
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
    s = s.reshape(*estimate.shape[:2], *s.shape[-2:])  # (C, k, h', w')
    if mask is not None:
        m = mask.to(s.device).to(s.dtype).expand_as(s)
        return (s * m).double().sum((0, 2, 3)).cpu().numpy(), m.sum((0, 2, 3)).cpu().numpy()
    return s.double().sum((0, 2, 3)).cpu().numpy(), np.full(s.shape[1], s[:, 0].numel(), dtype=np.float64)


def video_metrics(estimate: Tensor, truth: Tensor, intermediate: np.ndarray,
                  mask: Tensor | None = None, ssim: bool = True) -> dict[str, float]:
    """PSNR/SSIM over all frames and over the intermediate frames (away from GS key frames);
    `ssim=False`: PSNR only (SSIM's filtering is most of an evaluation's cost)."""
    out = {"psnr_db": psnr(estimate, truth, mask)}
    if len(intermediate):
        out["psnr_intermediate_db"] = psnr(estimate, truth, mask, frames=intermediate)
    if ssim:
        sums, counts = ssim_frame_sums(estimate, truth, mask)  # one filtering pass serves both frame sets
        out["ssim"] = float(sums.sum() / counts.sum())
        if len(intermediate):
            j = np.asarray(intermediate)
            out["ssim_intermediate"] = float(sums[j].sum() / counts[j].sum())
    return out


def relative_residual(pred: Tensor, meas: Tensor) -> float:
    """||pred - meas|| / ||meas|| (0/0 -> 0, x/0 -> inf)."""
    num = float(torch.linalg.vector_norm((pred - meas).double()))
    den = float(torch.linalg.vector_norm(meas.double()))
    if den == 0:
        return 0.0 if num == 0 else float("inf")
    return num / den


# The truth's prediction may differ from a measurement by up to this many times the noise
# estimated from the measurement itself before the data are called inconsistent with the truth.
_CONSISTENT_NOISE_RATIO = 3.0


def _visibility_sensors(problem, frame_chunk: int | None) -> dict:
    """name -> (measurement, forward operator computing in float64, 0/1 valid mask or None) for the
    sensors in use; they take a chunk of frames at a time (GS: `frame_chunk`) and copy no whole video."""
    rs, gs = problem.rs_op(), problem.gs_op()
    # the RS operator sizes its own chunks (its kept scratch stays small in float64 too)
    sensors = {"rs": (problem.b_rs, lambda x: rs.A(x, dtype=torch.float64),
                      problem.rs_valid_mask()),
               "gs": (problem.b_gs, lambda x: gs_forward(gs, x, frame_chunk), problem.gs_valid_mask())}
    return {name: s for name, s in sensors.items() if s[0] is not None and s[0].numel()}


def gs_forward(op, video: Tensor, frame_chunk: int | None = None, dtype=torch.float64) -> Tensor:
    """The GS operator's A(video) computed in `dtype`, `frame_chunk` frames at a time (default:
    `metric_chunk_frames`: the einsum's permuted copies of 16 frames had raised a large grid's peak by 0.2 GiB;
    no cast copy of the whole video)."""
    w = op.weights.to(dtype=dtype, device=video.device)
    step = frame_chunk or metric_chunk_frames(video)
    out = None
    for i in range(0, video.shape[1], step):
        part = torch.einsum("ckhw,gk->cghw", video[:, i:i + step].to(dtype), w[:, i:i + step])
        out = part if out is None else out.add_(part)
    return out


def _masked(y: Tensor, mask: Tensor | None) -> Tensor:
    return y if mask is None else y * mask.to(y.device, y.dtype)


def _noise_estimate_norm(name: str, meas: Tensor, mask: Tensor | None) -> float:
    """||noise|| expected on the measurement, from the measurement alone (rngcam.recon.noise)."""
    if name == "rs":
        std = row_noise_std(meas)
    else:
        std = float(np.mean([image_noise_std(meas[:, g]) for g in range(meas.shape[1])]))
    count = float(meas.numel() if mask is None else mask.expand_as(meas).sum())
    return std * math.sqrt(count)


def error_visibility(problem, estimate: Tensor, frame_chunk: int | None = None) -> dict[str, float]:
    """What each measurement sees of an estimate's error, in units of its noise: per sensor
    ("rs", "gs"), ||M A (estimate - truth)|| / ||M (A truth - b)|| (needs the truth; gains taken
    as 1), M the pixels that carry linear information (Problem.rs_valid / gs_valid).

    Below 1 the error hides under the measurement's noise: no closer fit to the data can find it,
    only a better prior. inf when a measurement has no noise but sees the error; nan without truth,
    and nan when the data cannot vouch for anything: the truth's prediction differs from the
    measurement by more than a few times the noise estimated from the measurement alone
    (mis-scaled or broken data; `error_visibility_caveats` says which). The operators take a
    chunk of frames at a time (GS: `frame_chunk`), in float64, so memory does not grow with K.
    """
    sensors = _visibility_sensors(problem, frame_chunk)
    if problem.truth is None:
        return {name: math.nan for name in sensors}
    truth = problem.truth
    out = {}
    for name, (meas, forward, mask) in sensors.items():  # A is linear: A(e - t) = A(e) - A(t), in float64
        predicted = forward(truth)
        signal = float(torch.linalg.vector_norm(_masked(forward(estimate.to(truth.device)) - predicted, mask)))
        noise = float(torch.linalg.vector_norm(_masked(predicted - meas.double(), mask)))
        expected = _noise_estimate_norm(name, meas, mask)
        if noise > _CONSISTENT_NOISE_RATIO * expected and noise > 0:
            out[name] = math.nan
        else:
            out[name] = signal / noise if noise > 0 else (0.0 if signal == 0 else math.inf)
    return out


def error_visibility_caveats(problem, frame_chunk: int | None = None) -> list[str]:
    """Why `error_visibility` cannot vouch for a result: data inconsistent with the truth (by how
    many times their noise), pixels or measurements left out. [] when there is nothing to say."""
    if problem.truth is None:
        return []
    out = []
    for name, (meas, forward, mask) in _visibility_sensors(problem, frame_chunk).items():
        noise = float(torch.linalg.vector_norm(_masked(forward(problem.truth) - meas.double(), mask)))
        expected = _noise_estimate_norm(name, meas, mask)
        if noise > _CONSISTENT_NOISE_RATIO * expected and noise > 0:
            ratio = f"{noise / expected:.3g}x" if expected > 0 else "infinitely many times"
            out.append(f"the {name.upper()} data differ from the truth's prediction by {ratio} their "
                       "noise (mis-scaled or broken data): its visibility is not reported")
        if mask is not None:
            frac = 1 - float(mask.mean())
            out.append(f"{100 * frac:.2f} % of the {name.upper()} pixels are left out (saturated "
                       "or clipped): the visibility covers the rest only")
    for what, why in getattr(problem, "left_out", []):
        out.append(f"{what} left out ({why}): the visibility does not cover it")
    return out


# ----------------------------------------------------------------------------- motion yardstick

DYNAMIC_THRESHOLD = 0.02  # |truth - its temporal median| above this (data range 1) counts as moving
DYNAMIC_DILATION_PX = 2  # the moving region grows by this much (the object's soft edge, small shifts)
GHOST_DILATION_PX = 2
OBJECT_FRACTION = 0.1  # an object pixel carries at least this share of the frame's peak object signal
ONE_OBJECT_SCENES = ("sineball",)  # simulated scenes with one moving object over a static background


def one_object_scene(rig_yaml: str) -> bool:
    """True for a bundle simulated from a one-object scene (its rig's mock scene, ONE_OBJECT_SCENES)."""
    try:
        rig = load_yaml(rig_yaml or "", "the bundle's rig text") or {}  # sized and depth-checked first
    except RngcamError:
        return False
    mock = rig.get("mock") if isinstance(rig, dict) else None
    return isinstance(mock, dict) and mock.get("scene") in ONE_OBJECT_SCENES


def _dilate(mask: Tensor, px: int) -> Tensor:
    """(K, H, W) boolean mask grown by px pixels (square structuring element)."""
    if px <= 0:
        return mask
    out = torch.empty_like(mask, dtype=torch.bool)
    step = metric_chunk_frames(mask, 4)
    for i in range(0, mask.shape[0], step):  # frame chunks: float temporaries of a few frames, not of the video
        m = mask[i:i + step].float()[:, None]
        out[i:i + step] = torch.nn.functional.max_pool2d(m, 2 * px + 1, stride=1, padding=px)[:, 0] > 0
    return out


def dynamic_region(truth: Tensor, threshold: float = DYNAMIC_THRESHOLD,
                   dilation_px: int = DYNAMIC_DILATION_PX) -> Tensor:
    """(K, H, W) boolean: where the truth (C, K, H, W) differs from its own temporal median by more
    than `threshold` in any channel, grown by `dilation_px` pixels: the moving region, per frame."""
    background = temporal_median(truth).double()  # (C, H, W)
    step = metric_chunk_frames(truth)
    moving = torch.cat([(truth[:, i:i + step].double() - background[:, None]).abs().amax(0) > threshold
                        for i in range(0, truth.shape[1], step)])  # frame chunks: bounded temporaries
    return _dilate(moving, dilation_px)


def temporal_median(video: Tensor, rows: int = 16) -> Tensor:
    """(C, H, W) median over time of a (C, K, H, W) video, `rows` image rows at a time (the
    median sorts a copy of what it is given)."""
    out = torch.empty(video.shape[0], *video.shape[2:], dtype=video.dtype, device=video.device)
    for y in range(0, video.shape[2], rows):
        # contiguous: a median over a stride-0 (expanded) axis comes out wrong
        out[:, y:y + rows] = video[:, :, y:y + rows].contiguous().median(dim=1).values
    return out


def psnr_dynamic(estimate: Tensor, truth: Tensor, frames: np.ndarray | None = None) -> float:
    """PSNR in dB over the moving region (`dynamic_region`) of `frames` (default all); nan when
    nothing moves there."""
    region = dynamic_region(truth)
    idx = torch.arange(truth.shape[1]) if frames is None else torch.as_tensor(np.asarray(frames), dtype=torch.long)
    total, count = 0.0, 0
    step = metric_chunk_frames(truth)
    for i in range(0, len(idx), step):  # a few frames at a time: bounded float64 temporaries at any size
        j = idx[i:i + step].to(truth.device)
        r = region.index_select(0, j)[None]
        e = estimate.index_select(1, j.to(estimate.device)).double().to(truth.device)
        diff = (e - truth.index_select(1, j).double()) ** 2
        total, count = total + float(diff[r.expand_as(diff)].sum()), count + int(r.sum()) * diff.shape[0]
    if count == 0:
        return math.nan
    mse = total / count
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def object_signal(video: Tensor, background: Tensor) -> Tensor:
    """(K, H, W): how far each pixel of a video (C, K, H, W) is from a static background (C, H, W),
    summed over channels (the moving object's footprint, whatever its colour)."""
    return (video.double() - background.double()[:, None]).abs().sum(0)


def _centroids(weights: Tensor) -> Tensor:
    """(K, 2) weighted centroid (x, y) in pixels of (K, H, W) non-negative weights (nan if empty)."""
    k, h, w = weights.shape
    total = weights.sum((1, 2))
    ys = torch.arange(h, dtype=weights.dtype, device=weights.device)
    xs = torch.arange(w, dtype=weights.dtype, device=weights.device)
    cx = (weights.sum(1) * xs).sum(1) / total
    cy = (weights.sum(2) * ys).sum(1) / total
    out = torch.stack([cx, cy], dim=1)
    out[total <= 0] = math.nan
    return out


def object_metrics(estimate: Tensor, truth: Tensor, frames: np.ndarray | None = None) -> dict[str, float]:
    """For a scene with one moving object over a static background: per frame, the distance in
    pixels between the object's centroid in the estimate and in the truth (median and 90th
    percentile over `frames`), and the ghost figure: the share of the estimate's object signal
    outside the true object region grown by GHOST_DILATION_PX pixels (median and maximum over
    `frames`; a split or smeared object puts signal there).

    The background is the truth's temporal median. Object signal is |video - background| summed
    over channels, less OBJECT_FRACTION of the truth's peak object signal in that frame (so the
    estimate's faint noise over the whole image does not count as object). Frame by frame: no
    video-sized temporaries.
    """
    background = temporal_median(truth).double()
    idx = torch.arange(truth.shape[1]) if frames is None else torch.as_tensor(np.asarray(frames), dtype=torch.long)
    errs, ghosts = [], []
    step = metric_chunk_frames(truth)
    for i in range(0, len(idx), step):
        j = idx[i:i + step]
        s_true = object_signal(truth.index_select(1, j.to(truth.device)), background)
        s_est = object_signal(estimate.index_select(1, j.to(estimate.device)).to(truth.device), background)
        floor = OBJECT_FRACTION * s_true.amax((1, 2), keepdim=True)
        w_true, w_est = (s_true - floor).clamp_min(0), (s_est - floor).clamp_min(0)
        region = _dilate(w_true > 0, GHOST_DILATION_PX)
        errs.append((_centroids(w_est) - _centroids(w_true)).norm(dim=1).cpu())
        total = w_est.sum((1, 2))
        ghosts.append(torch.where(total > 0, (w_est * ~region).sum((1, 2)) / total.clamp_min(1e-30),
                                  torch.ones_like(total)).cpu())
    err = torch.cat(errs).cpu().numpy() if errs else np.zeros(0)
    ghost = torch.cat(ghosts).cpu().numpy() if ghosts else np.zeros(0)
    finite = err[np.isfinite(err)]
    if finite.size < err.size:  # an estimate without any object in a frame: the worst case
        finite = np.concatenate([finite, np.full(err.size - finite.size, math.inf)])
    return {"centroid_error_median_px": float(np.median(finite)) if finite.size else math.nan,
            "centroid_error_p90_px": float(np.percentile(finite, 90)) if finite.size else math.nan,
            "ghost_median": float(np.median(ghost)) if ghost.size else math.nan,
            "ghost_max": float(np.max(ghost)) if ghost.size else math.nan}


def motion_metrics(estimate: Tensor, truth: Tensor, intermediate: np.ndarray,
                   one_object: bool = False) -> dict[str, float]:
    """The motion yardstick over the intermediate frames: `psnr_dynamic_db`, and with
    `one_object` the centroid and ghost figures of `object_metrics`."""
    frames = np.asarray(intermediate) if len(intermediate) else None
    out = {"psnr_dynamic_db": psnr_dynamic(estimate, truth, frames)}
    if one_object:
        out.update(object_metrics(estimate, truth, frames))
    return out
