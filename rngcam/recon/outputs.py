"""Reconstruction outputs: recon.h5, MP4 preview, TIFF stack, metrics.json, errors.csv/png.

The video is (C, K, H, W) linear intensity. Previews (MP4, plots) are gamma-encoded for display;
recon.h5 and the TIFF stack keep linear float32.
"""

from __future__ import annotations

import csv
import json
import math
import os
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from rngcam.version import __version__


def _atomic_h5(path: Path):
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    return tmp, h5py.File(tmp, "w")


def write_recon_h5(path: Path, video: np.ndarray, frame_times_s: np.ndarray, settings: dict,
                   bundle_checksum: str, components: dict[str, np.ndarray] | None = None,
                   left_out: list | None = None) -> None:
    """recon.h5: video, frame times, components, resolved settings, input checksum (atomic)."""
    tmp, f = _atomic_h5(path)
    try:
        with f:
            f.attrs["format"] = "rngcam-recon"
            f.attrs["rngcam_version"] = __version__
            f.attrs["created_utc"] = datetime.now(timezone.utc).isoformat()
            f.attrs["bundle_sha256"] = bundle_checksum
            f.attrs["settings"] = json.dumps(settings, default=str)
            f.attrs["left_out"] = json.dumps(left_out or [])
            f.create_dataset("video", data=video.astype(np.float32), chunks=(video.shape[0], 1, *video.shape[2:]))
            f["frame_times_s"] = np.asarray(frame_times_s, np.float64)
            for name, arr in (components or {}).items():
                f[f"components/{name}"] = np.asarray(arr, np.float32)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def to_display(video: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """(C, K, H, W) linear -> (K, H, W, 3) uint8 gamma-encoded (mono repeated to RGB)."""
    v = np.clip(np.nan_to_num(video, nan=0.0), 0, 1) ** (1 / gamma)
    v = np.moveaxis(v, 0, -1)
    if v.shape[-1] == 1:
        v = np.repeat(v, 3, axis=-1)
    return (v * 255 + 0.5).astype(np.uint8)


def playback(capture_fps: float | None, fps: float = 30.0) -> dict:
    """What a preview's time axis means: capture and playback rates and the slow-down."""
    out = {"playback_fps": float(fps)}
    if capture_fps is not None and math.isfinite(capture_fps) and capture_fps > 0:
        out.update(capture_fps=float(capture_fps), frame_interval_s=1.0 / capture_fps,
                   slowdown=float(capture_fps) / fps)
    return out


def write_mp4(path: Path, video: np.ndarray, fps: float = 30.0, capture_fps: float | None = None) -> None:
    """H.264 preview via PyAV; sides are padded to even sizes and small videos upscaled.

    With `capture_fps`, the container's metadata (title, comment) state the capture frame rate
    and the slow-down, and a sidecar `<name>.json` beside it repeats them for tools that do not
    read MP4 metadata.
    """
    import av

    frames = to_display(video)
    _k, h, w, _ = frames.shape
    scale = max(1, 256 // max(h, w))
    frames = np.repeat(np.repeat(frames, scale, axis=1), scale, axis=2)
    h2, w2 = frames.shape[1] + frames.shape[1] % 2, frames.shape[2] + frames.shape[2] % 2
    frames = np.pad(frames, ((0, 0), (0, h2 - frames.shape[1]), (0, w2 - frames.shape[2]), (0, 0)))
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}.mp4")
    timing = playback(capture_fps, fps)
    with av.open(str(tmp), "w") as out:
        if "capture_fps" in timing:
            note = (f"captured at {timing['capture_fps']:,.1f} fps, played at {fps:g} fps: "
                    f"{timing['slowdown']:,.1f}x slow motion")
            out.metadata["title"] = f"rngcam reconstruction ({note})"
            out.metadata["comment"] = note
        stream = out.add_stream("libx264", rate=round(fps))
        stream.width, stream.height, stream.pix_fmt = w2, h2, "yuv420p"
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    os.replace(tmp, path)
    if "capture_fps" in timing:
        sidecar = path.with_suffix(".json")
        sidecar.write_text(json.dumps({"file": path.name, "frames": int(video.shape[1]), **timing}, indent=2))


def write_tiff(path: Path, video: np.ndarray, frame_interval_s: float | None = None) -> None:
    """Linear float32 ImageJ hyperstack (T, C, Y, X): frames as time, colour as channels, and
    with `frame_interval_s` the frame interval in seconds, so Fiji/napari show the capture's time."""
    import tifffile

    meta = {"axes": "TCYX", "mode": "composite" if video.shape[0] > 1 else "grayscale", "unit": "pixel"}
    if frame_interval_s is not None and math.isfinite(frame_interval_s) and frame_interval_s > 0:
        meta.update(finterval=float(frame_interval_s), tunit="s")
    tifffile.imwrite(path, np.ascontiguousarray(np.moveaxis(video.astype(np.float32, copy=False), 0, 1)),
                     imagej=True, metadata=meta)


def write_errors(csv_path: Path, png_path: Path, log: list[dict], title: str = "") -> None:
    """errors.csv (one row per log entry) and errors.png (residuals and PSNR against solve time)."""
    keys: list[str] = []
    for row in log:
        keys += [k for k in row if k not in keys]
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(log)
    plot_errors(png_path, {title or "run": log})


def plot_errors(png_path: Path, runs: dict[str, list[dict]]) -> None:
    """One figure: relative residual per sensor (left) and PSNR (right) against solve time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_psnr = any("psnr_db" in r for log in runs.values() for r in log)
    fig, axes = plt.subplots(1, 2 if has_psnr else 1, figsize=(11 if has_psnr else 6, 4), squeeze=False)
    ax_r = axes[0, 0]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, log) in enumerate(runs.items()):
        c = colours[i % len(colours)]
        t = [max(r["solve_s"], 1e-3) for r in log]
        style = {"color": c, "marker": "o", "markersize": 3 if len(log) > 1 else 6}
        for key, ls in (("residual_rs", "-"), ("residual_gs", "--")):
            vals = [r.get(key, np.nan) for r in log]
            if np.isfinite(vals).any():
                ax_r.plot(t, vals, ls, label=f"{name} {key[9:].upper()}", **style)
        if has_psnr:
            ax_p = axes[0, 1]
            ax_p.plot(t, [r.get("psnr_db", np.nan) for r in log], "-", label=f"{name} all", **style)
            if any("psnr_intermediate_db" in r for r in log):
                ax_p.plot(t, [r.get("psnr_intermediate_db", np.nan) for r in log], ":",
                          label=f"{name} intermediate", **{**style, "marker": "x"})
    ax_r.set(xlabel="solve time (s)", ylabel="relative data residual", yscale="log", title="data residual")
    ax_r.legend(fontsize=7)
    if has_psnr:
        axes[0, 1].set(xlabel="solve time (s)", ylabel="PSNR (dB)", title="error against truth")
        axes[0, 1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


def write_metrics(path: Path, metrics: dict) -> None:
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(json.dumps(metrics, indent=2, default=float))
    os.replace(tmp, path)
