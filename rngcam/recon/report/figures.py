"""The report's pictures: frames as data URIs (downscaled when large), per-frame figures against
the truth, the error-against-time plot and STFM's parts. Everything is returned embedded."""

from __future__ import annotations

import base64
import io
import math
import tempfile
from pathlib import Path

import numpy as np
import torch

from rngcam.recon.metrics import OBJECT_FRACTION, dynamic_region
from rngcam.recon.outputs import plot_errors, to_display
from rngcam.untrusted import printable

MAX_SIDE = 320  # frames larger than this are downscaled (the report says so)
MAX_FRAMES = 600  # longer videos show every n-th frame (the report says so)
PNG_BELOW_PX = 128 * 128  # small frames stay lossless PNG; larger ones are JPEG


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def frame_plan(k: int, h: int, w: int) -> tuple[np.ndarray, float, list[str]]:
    """Which frames the players show, the spatial factor, and notes saying what was reduced."""
    stride = max(1, math.ceil(k / MAX_FRAMES))
    factor = min(1.0, MAX_SIDE / max(h, w))
    notes = []
    if stride > 1:
        notes.append(f"players show every {stride}th of the {k} frames (at most {MAX_FRAMES}); "
                     f"recon.h5 has them all")
    if factor < 1:
        notes.append(f"frames downscaled from {w}x{h} to {round(w * factor)}x{round(h * factor)} px "
                     f"for the page; recon.h5 and video.tif are full size")
    if h * w * factor * factor > PNG_BELOW_PX:
        notes.append("frames are JPEG (quality 85); recon.h5 and video.tif keep the linear values")
    return np.arange(0, k, stride), factor, notes


def encode_images(rgb: np.ndarray, factor: float = 1.0) -> list[str]:
    """(N, H, W, 3) uint8 -> data URIs (PNG when small, else JPEG), resized by `factor`."""
    import cv2  # heavy: cv2

    out = []
    for img in rgb:
        if factor < 1:
            img = cv2.resize(img, (round(img.shape[1] * factor), round(img.shape[0] * factor)),
                             interpolation=cv2.INTER_AREA)
        bgr = np.ascontiguousarray(img[..., ::-1])
        if img.shape[0] * img.shape[1] <= PNG_BELOW_PX:
            ok, buf = cv2.imencode(".png", bgr)
            mime = "image/png"
        else:
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 85])
            mime = "image/jpeg"
        if not ok:
            raise RuntimeError("image encoding failed")
        out.append(data_uri(buf.tobytes(), mime))
    return out


CHUNK = 16  # frames read, converted and encoded at a time: no video-sized temporaries


def video_uris(video: np.ndarray, frames: np.ndarray, factor: float, scale: float = 1.0) -> list[str]:
    """The chosen frames of a (C, K, H, W) linear video (or recon.h5's, read on demand),
    gamma-encoded, as data URIs."""
    return [uri for i in range(0, len(frames), CHUNK)
            for uri in encode_images(to_display(video[:, frames[i:i + CHUNK]] * scale), factor)]


def map_uris(maps: np.ndarray, factor: float, vmax: float, cmap: str = "magma") -> list[str]:
    """(N, H, W) scalar maps through a colour map (0..vmax) as data URIs."""
    import matplotlib  # heavy: matplotlib

    out = []
    for i in range(0, len(maps), CHUNK):  # the colour map makes float64 RGBA: a chunk at a time
        norm = np.clip(np.nan_to_num(maps[i:i + CHUNK]) / (vmax if vmax > 0 else 1.0), 0, 1)
        out += encode_images((matplotlib.colormaps[cmap](norm)[..., :3] * 255 + 0.5).astype(np.uint8), factor)
    return out


def chunked_map_uris(maps, index: int, frames: np.ndarray, factor: float, vmax: float,
                     cmap: str = "magma") -> list[str]:
    """`map_uris` of channel `index` of a (C, K, H, W) map (or recon.h5's, read on demand) at `frames`,
    read and encoded CHUNK frames at a time."""
    return [uri for i in range(0, len(frames), CHUNK)
            for uri in map_uris(np.asarray(maps[index, frames[i:i + CHUNK]]), factor, vmax, cmap)]


def speed_over_time(motion, frames: np.ndarray, factor: float) -> tuple[list[str], dict[str, np.ndarray], float]:
    """A (2, K, H, W) motion in px (or recon.h5's, read on demand): its speed |motion| at `frames` as
    data URIs (0 to its largest), its mean, 99th percentile and maximum per frame, and that largest
    speed. Read CHUNK frames at a time, twice (the scale first): no video-sized speed array."""
    k = motion.shape[1]
    stats = {"mean": np.zeros(k), "99th percentile": np.zeros(k), "max": np.zeros(k)}
    for i in range(0, k, CHUNK):
        speed = np.linalg.norm(np.asarray(motion[:, i:i + CHUNK]), axis=0)  # (n, H, W)
        stats["mean"][i:i + CHUNK] = speed.mean((1, 2))
        stats["99th percentile"][i:i + CHUNK] = np.percentile(speed, 99, (1, 2))
        stats["max"][i:i + CHUNK] = speed.max((1, 2))
    top = float(np.max(stats["max"])) if k else 0.0
    uris = []
    for i in range(0, len(frames), CHUNK):
        speed = np.linalg.norm(np.asarray(motion[:, frames[i:i + CHUNK]]), axis=0)
        uris += map_uris(speed, factor, top)
    return uris, stats, top


def _psnr(err2: np.ndarray) -> float:
    mse = float(np.mean(err2)) if err2.size else math.nan
    return math.inf if mse == 0 else (10 * math.log10(1 / mse) if math.isfinite(mse) else math.nan)


def _centroids(w: np.ndarray) -> np.ndarray:
    total = w.sum((1, 2))
    ys, xs = np.arange(w.shape[1]), np.arange(w.shape[2])
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = (w.sum(1) * xs).sum(1) / total
        cy = (w.sum(2) * ys).sum(1) / total
    out = np.stack([cx, cy], 1)
    out[total <= 0] = np.nan
    return out


def _median_over_time(video: np.ndarray, rows: int = 16) -> np.ndarray:
    """np.median over axis 1 of (C, K, H, W), a block of rows at a time (median sorts a copy)."""
    out = np.empty((video.shape[0], *video.shape[2:]), np.float32)
    for y in range(0, video.shape[2], rows):
        out[:, y:y + rows] = np.median(video[:, :, y:y + rows], axis=1)
    return out


def per_frame(video: np.ndarray, truth: np.ndarray, one_object: bool) -> dict[str, np.ndarray]:
    """Per frame: PSNR (dB) over the image and over the moving region (where the truth differs
    from its temporal median, as in metrics.json's psnr_dynamic_db) and, for a one-object scene,
    the object's centroid error in pixels (as centroid_error_*_px). A frame at a time: `video`
    may be recon.h5's, read on demand."""
    k_all = video.shape[1]
    truth_t = torch.from_numpy(np.asarray(truth))
    moving = dynamic_region(truth_t).numpy()  # (K, H, W)
    bg = _median_over_time(truth) if one_object else None
    psnr_all, psnr_moving = np.full(k_all, np.nan), np.full(k_all, np.nan)
    centroid_error = np.full(k_all, np.nan)
    for k in range(k_all):  # a frame at a time: no video-sized float64 copies
        est = np.nan_to_num(np.asarray(video[:, k], np.float32), nan=0.0)
        err2 = (est.astype(np.float64) - truth[:, k]) ** 2
        psnr_all[k] = _psnr(err2)
        if moving[k].any():
            psnr_moving[k] = _psnr(err2[:, moving[k]])
        if one_object:
            s_true = np.abs(truth[:, k] - bg).sum(0)  # object_signal in float32: (H, W)
            s_est = np.abs(est - bg).sum(0)
            floor = OBJECT_FRACTION * s_true.max()
            c_t = _centroids(np.clip(s_true - floor, 0, None).astype(np.float64)[None])
            c_e = _centroids(np.clip(s_est - floor, 0, None).astype(np.float64)[None])
            centroid_error[k] = np.linalg.norm(c_e - c_t, axis=1)[0]
    out = {"psnr_db": psnr_all, "psnr_moving_db": psnr_moving}
    if one_object:
        out["centroid_error_px"] = centroid_error
    return out


def plain(text: object) -> str:
    """A label from a file as matplotlib text: `$` escaped (no mathtext parse of someone else's
    string) and control characters shown escaped."""
    return printable(text, 200).replace("$", r"\$")


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return data_uri(buf.getvalue(), "image/png")


def time_plot(times_us: np.ndarray, series: dict[str, dict[str, np.ndarray]], key_us: np.ndarray,
              panels: list[tuple[str, str]], dt_us: float) -> dict:
    """Figures against frame time, one panel per (key, y label); series: name -> key -> values.
    Returns the PNG's data URI and where its time axis lies (fractions of the image's width), so
    the page can draw the current frame over it."""
    import matplotlib  # heavy: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib

    panels = [(k, lab) for k, lab in panels if any(k in s for s in series.values())]
    if not panels:
        return {}
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.1 * len(panels) + 0.5), sharex=True, squeeze=False)
    lo, hi = times_us[0] - dt_us / 2, times_us[-1] + dt_us / 2
    for ax, (key, label) in zip(axes[:, 0], panels):
        for i, (name, s) in enumerate(series.items()):
            if key in s:
                ax.plot(times_us, s[key], "-", lw=1.2, color=f"C{i % 10}", label=plain(name))
        for t in key_us:
            ax.axvspan(t - dt_us / 2, t + dt_us / 2, color="0.85", zorder=0)
        ax.set(ylabel=label, xlim=(lo, hi))
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=min(4, len(series)), loc="best")
    axes[-1, 0].set_xlabel("frame time (µs from the RS trigger; grey: GS key frames)")
    fig.tight_layout()
    box = axes[0, 0].get_position()
    uri = _png(fig)
    plt.close(fig)
    return {"uri": uri, "x0": box.x0, "x1": box.x1, "t0": lo, "t1": hi}


def errors_plot(logs: dict[str, list[dict]], noise_level: float | None) -> str:
    """outputs.plot_errors (error against run time, the noise level drawn) as a data URI."""
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / "errors.png"
        plot_errors(png, {plain(name): log for name, log in logs.items()}, noise_level=noise_level)
        return data_uri(png.read_bytes(), "image/png")


def image_figure(images: dict[str, np.ndarray], title: str = "") -> str:
    """A row of (C, H, W) linear images (gamma-encoded) with their names, as a data URI."""
    import matplotlib  # heavy: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib

    fig, axes = plt.subplots(1, len(images), figsize=(2.6 * len(images), 2.9), squeeze=False)
    for ax, (name, img) in zip(axes[0], images.items()):
        ax.imshow(to_display(img[:, None])[0], interpolation="nearest")
        ax.set_title(plain(name), fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
    if title:
        fig.suptitle(plain(title), fontsize=9)
    fig.tight_layout()
    uri = _png(fig)
    plt.close(fig)
    return uri
