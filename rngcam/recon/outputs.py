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
from fractions import Fraction
from pathlib import Path

import h5py
import numpy as np

from rngcam.errors import ConfigError, RngcamError
from rngcam.untrusted import replacing, write_new
from rngcam.version import __version__

# What the numbers in recon.h5 mean, for tools that read its attributes (napari, h5py, Fiji's HDF5).
INTENSITY_UNIT = ("linear; 1.0 = a static scene that fills the sensor's full scale (above the black level) "
                  "in the camera's exposure")
FRAME_TIMES_NOTE = "centre of each frame's interval [k dt, (k+1) dt), in seconds from T0 (the RS trigger)"


def recon_context(bundle_path: Path | None, bundle, problem) -> dict:
    """What a recon folder records of its input beyond the video: the bundle's absolute path and
    capture time, the grid's frame interval, the GS key frames and their times, the RS image
    (grid units), its relative noise level (where STFM's and pnp's stop aims) and, when the bundle
    states it (meta `pixel_size_m`: the scene's size of one RS sensor pixel), that of one grid pixel."""
    from rngcam.recon.noise import relative_noise_level  # heavy: noise loads torch

    ctx = {"bundle_path": str(Path(bundle_path).resolve()) if bundle_path is not None else "",
           "capture_utc": (bundle.created_utc or "") if bundle is not None else "",
           "dt_s": float(problem.grid.dt_s), "key_frame_times_s": np.asarray(problem.gs_times_s, np.float64)}
    if problem.b_gs is not None and problem.b_gs.shape[1]:
        ctx["key_frames"] = problem.to_sensor(problem.gs_images().cpu().float().numpy())
    if problem.b_rs is not None:
        ctx["rs_image"] = problem.to_sensor(problem.b_rs.cpu().float().numpy())
        ctx["rs_noise_level"] = relative_noise_level(problem.b_rs)
    size = (bundle.meta or {}).get("pixel_size_m") if bundle is not None else None
    if isinstance(size, (int, float)) and math.isfinite(size) and size > 0:
        sensor_rows = bundle.rs.frames.shape[1] if bundle.rs is not None else problem.shape[2]
        grid_rows = problem.shape[3 if problem.transposed else 2]
        ctx["pixel_size_m"] = float(size) * sensor_rows / grid_rows  # one grid pixel
    return ctx


def _set_axes(ds, labels: str, **attrs) -> None:
    ds.attrs["axes"] = labels
    for i, label in enumerate(labels.split(",")):
        ds.dims[i].label = label
    for k, v in attrs.items():
        ds.attrs[k] = v


def write_recon_h5(path: Path, video: np.ndarray, frame_times_s: np.ndarray, settings: dict,
                   bundle_checksum: str, components: dict[str, np.ndarray] | None = None,
                   left_out: list | None = None, context: dict | None = None,
                   results: dict | None = None) -> None:
    """recon.h5: video, frame times, components, resolved settings and, apart from them, what the
    run found (`results`: status, how it ended, the method's results, events), input checksum (atomic).

    Every dataset says its axes and units in attributes; `context` (recon_context) adds the
    bundle's path and capture time, the key frames and their times, and the RS image."""
    ctx = context or {}
    # h5py follows a link at the name it creates: it writes a fresh temporary file, renamed onto `path`
    with replacing(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = "rngcam-recon"
        f.attrs["rngcam_version"] = __version__
        f.attrs["created_utc"] = datetime.now(timezone.utc).isoformat()
        f.attrs["bundle_sha256"] = bundle_checksum
        f.attrs["bundle_path"] = ctx.get("bundle_path", "")
        f.attrs["capture_utc"] = ctx.get("capture_utc", "")
        f.attrs["settings"] = json.dumps(settings, default=str)
        f.attrs["left_out"] = json.dumps(left_out or [])
        f.attrs["results"] = json.dumps(results or {}, default=str)
        times = np.asarray(frame_times_s, np.float64)
        dt = ctx.get("dt_s", float(np.median(np.diff(times))) if times.size > 1 else float("nan"))
        f.attrs["frame_interval_s"] = dt
        f.attrs["fps"] = 1.0 / dt if dt > 0 else float("nan")
        if "rs_noise_level" in ctx:
            f.attrs["rs_noise_level"] = ctx["rs_noise_level"]
        if "pixel_size_m" in ctx:
            f.attrs["pixel_size_m"] = ctx["pixel_size_m"]
        ds = f.create_dataset("video", shape=video.shape, dtype=np.float32,
                              chunks=(video.shape[0], 1, *video.shape[2:]))
        for k in range(0, video.shape[1], DISPLAY_CHUNK):  # a float32 copy of a chunk at a time
            ds[:, k:k + DISPLAY_CHUNK] = np.asarray(video[:, k:k + DISPLAY_CHUNK], np.float32)
        channels = "R,G,B" if video.shape[0] == 3 else ",".join(f"c{i}" for i in range(video.shape[0]))
        _set_axes(ds, "C,T,Y,X", channels=channels, intensity_unit=INTENSITY_UNIT,
                  display_range=np.array([0.0, 1.0]), time_source="frame_times_s")
        f["frame_times_s"] = times
        _set_axes(f["frame_times_s"], "T", units="s", meaning=FRAME_TIMES_NOTE)
        if "key_frame_times_s" in ctx:
            f["key_frame_times_s"] = np.asarray(ctx["key_frame_times_s"], np.float64)
            _set_axes(f["key_frame_times_s"], "G", units="s",
                      meaning="mid-exposure time of each GS key frame, seconds from T0")
        if "key_frames" in ctx:
            f["key_frames"] = np.asarray(ctx["key_frames"], np.float32)
            _set_axes(f["key_frames"], "C,G,Y,X", intensity_unit=INTENSITY_UNIT)
        if "rs_image" in ctx:
            f["rs_image"] = np.asarray(ctx["rs_image"], np.float32)
            _set_axes(f["rs_image"], "C,Y,X", intensity_unit="the RS measurement on the grid, "
                      "operator units (a sum over the frames each row's exposure covers)")
        for name, arr in (components or {}).items():
            f[f"components/{name}"] = np.asarray(arr, np.float32)  # no copy when float32 already


DISPLAY_CHUNK = 16  # frames converted at a time: float temporaries of 16 frames, not of the video


def to_display(video: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """(C, K, H, W) linear -> (K, H, W, 3) uint8 gamma-encoded (mono repeated to RGB)."""
    c, k, h, w = video.shape
    out = np.empty((k, h, w, 3), np.uint8)
    for i in range(0, k, DISPLAY_CHUNK):
        v = np.clip(np.nan_to_num(np.asarray(video[:, i:i + DISPLAY_CHUNK], np.float32), nan=0.0), 0, 1)
        v = np.moveaxis(v ** (1 / gamma), 0, -1)
        out[i:i + DISPLAY_CHUNK] = v * 255 + 0.5  # cast on assignment; mono broadcasts to RGB
    return out


def playback(capture_fps: float | None, fps: float = 30.0) -> dict:
    """What a preview's time axis means: capture and playback rates and the slow-down."""
    out = {"playback_fps": float(fps)}
    if capture_fps is not None and math.isfinite(capture_fps) and capture_fps > 0:
        out.update(capture_fps=float(capture_fps), frame_interval_s=1.0 / capture_fps,
                   slowdown=float(capture_fps) / fps)
    return out


def stamp_frames(frames: np.ndarray, times_s: np.ndarray, key_times_s: np.ndarray | None = None,
                 dt_s: float | None = None) -> np.ndarray:
    """(K, H, W, 3) uint8 display frames with each frame's time (µs from T0) written in its top
    left corner, and "GS" after it on the frames whose interval holds a key frame's centre."""
    import cv2  # heavy: cv2

    out = frames.copy()
    h = out.shape[1]
    scale = max(0.35, h / 256 * 0.45)
    thick = max(1, round(h / 256))
    keys = np.asarray(key_times_s if key_times_s is not None else [], np.float64)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k, t in enumerate(np.asarray(times_s, np.float64)):
        text = f"{t * 1e6:,.1f} us"
        if dt_s and keys.size and np.any(np.abs(keys - t) <= dt_s / 2):
            text += " GS"
        (tw, th), base = cv2.getTextSize(text, font, scale, thick)
        out[k, :th + base + 4, :tw + 6] //= 3  # a dark box under the text: legible on any frame
        cv2.putText(out[k], text, (3, th + 2), font, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return out


def write_mp4(path: Path, video: np.ndarray, fps: float = 30.0, capture_fps: float | None = None,
              frame_times_s: np.ndarray | None = None, key_times_s: np.ndarray | None = None,
              replace: bool = True) -> None:
    """H.264 preview via PyAV played at `fps`; sides are padded to even sizes and small videos
    upscaled. With `frame_times_s`, each frame is stamped with its time in µs (and "GS" where a
    key frame sits: `key_times_s`).

    With `capture_fps`, the container's metadata (title, comment) state the capture frame rate
    and the slow-down, and a sidecar `<name>.json` beside it repeats them for tools that do not
    read MP4 metadata. Both are written beside and renamed into place; without `replace` an
    existing file of either name is refused in one line (before anything is written).
    """
    import av  # heavy: av

    if not (math.isfinite(fps) and fps > 0):
        raise ConfigError(f"playback fps must be a positive number, got {fps}")
    _c, k, h, w = video.shape
    scale = max(1, 256 // max(h, w))
    h2, w2 = h * scale + h * scale % 2, w * scale + w * scale % 2
    dt = 1.0 / capture_fps if capture_fps else None

    def display(i: int) -> np.ndarray:  # DISPLAY_CHUNK frames from i, upscaled, padded and stamped
        frames = to_display(video[:, i:i + DISPLAY_CHUNK])
        frames = np.repeat(np.repeat(frames, scale, axis=1), scale, axis=2)
        frames = np.pad(frames, ((0, 0), (0, h2 - frames.shape[1]), (0, w2 - frames.shape[2]), (0, 0)))
        if frame_times_s is not None:
            frames = stamp_frames(frames, frame_times_s[i:i + DISPLAY_CHUNK], key_times_s, dt)
        return frames

    timing = playback(capture_fps, fps)
    sidecar = path.with_suffix(".json")
    if sidecar == path:
        raise ConfigError(f"a preview's name must not end in .json (its sidecar is <name>.json): {path}")
    written = (path, sidecar) if "capture_fps" in timing else (path,)
    for p in written if not replace else ():
        if os.path.lexists(p):
            raise RngcamError(f"refusing to replace {p}: it exists (pass --overwrite to replace it)")
    with replacing(path, replace=replace) as tmp, av.open(str(tmp), "w", format="mp4") as out:
        if "capture_fps" in timing:
            note = (f"captured at {timing['capture_fps']:,.1f} fps, played at {fps:g} fps: "
                    f"{timing['slowdown']:,.1f}x slow motion")
            out.metadata["title"] = f"rngcam reconstruction ({note})"
            out.metadata["comment"] = note
        stream = out.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height, stream.pix_fmt = w2, h2, "yuv420p"
        for i in range(0, k, DISPLAY_CHUNK):
            for frame in display(i):
                for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                    out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    if "capture_fps" in timing:
        write_new(sidecar, json.dumps({"file": path.name, "frames": int(video.shape[1]), **timing}, indent=2),
                  replace=replace)


def write_tiff(path: Path, video: np.ndarray, frame_interval_s: float | None = None,
               pixel_size_m: float | None = None) -> None:
    """Linear float32 ImageJ hyperstack (T, C, Y, X): frames as time, colour as channels, and
    with `frame_interval_s` the frame interval in seconds, so Fiji shows the capture's time;
    with `pixel_size_m` (one grid pixel in the scene) a spatial scale in µm, else pixels."""
    import tifffile  # heavy: tifffile

    meta = {"axes": "TCYX", "mode": "composite" if video.shape[0] > 1 else "grayscale", "unit": "pixel"}
    if frame_interval_s is not None and math.isfinite(frame_interval_s) and frame_interval_s > 0:
        meta.update(finterval=float(frame_interval_s), tunit="s")
    resolution = None
    if pixel_size_m is not None and math.isfinite(pixel_size_m) and pixel_size_m > 0:
        meta["unit"] = "um"
        per_um = 1.0 / (pixel_size_m * 1e6)
        resolution = (per_um, per_um)
    c, k, h, w = video.shape
    planes = (np.asarray(video[ch, t], np.float32) for t in range(k) for ch in range(c))  # no (T, C) copy
    with replacing(path) as tmp:
        tifffile.imwrite(tmp, planes, shape=(k, c, h, w), dtype=np.float32, imagej=True, metadata=meta,
                         resolution=resolution)


def write_errors(csv_path: Path, png_path: Path, log: list[dict], title: str = "",
                 noise_level: float | None = None) -> None:
    """errors.csv (one row per log entry) and errors.png (residuals and PSNR against run time,
    the RS noise level drawn where `noise_level` is known)."""
    keys: list[str] = []
    for row in log:
        keys += [k for k in row if k not in keys]
    with replacing(csv_path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(log)
    plot_errors(png_path, {title or "run": log}, noise_level=noise_level)


# RS and GS residuals differ by line and marker, not only by colour (colour is the method).
SENSOR_STYLE = {"residual_rs": ("-", "o", "RS"), "residual_gs": ("--", "s", "GS")}
ONE_SHOT_NOTE = ("a single point: a one-shot baseline, or a fit whose budget ended before its first "
                 "iteration (see events)")


def plot_errors(png_path: Path, runs: dict[str, list[dict]], noise_level: float | None = None) -> None:
    """One figure: relative residual per sensor (left) and PSNR (right) against run time.

    Run time is the method's own compute time with set-up included; each iterative run's first
    point (the end of its set-up) is marked with a bar. A run with one log row (a GS-only
    baseline, or a fit stopped before its first iteration) is one large marker with a note.
    `noise_level` (the RS image's relative noise level, where STFM's and pnp's stop aims) is a
    horizontal line."""
    import matplotlib  # heavy: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib

    has_psnr = any("psnr_db" in r for log in runs.values() for r in log)
    fig, axes = plt.subplots(1, 2 if has_psnr else 1, figsize=(11 if has_psnr else 6.5, 4.2), squeeze=False)
    ax_r = axes[0, 0]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    one_shot = []
    for i, (name, log) in enumerate(runs.items()):
        if not log:
            continue
        c = colours[i % len(colours)]
        t = [max(r["solve_s"], 1e-3) for r in log]
        single = len(log) == 1
        if single:
            one_shot.append(name)
        for key, (ls, marker, sensor) in SENSOR_STYLE.items():
            vals = [r.get(key, np.nan) for r in log]
            if not np.isfinite(vals).any():
                continue
            if single:
                ax_r.plot(t, vals, linestyle="none", marker="*" if sensor == "RS" else "P", ms=12, color=c,
                          mec="black", mew=0.6, label=f"{name} {sensor} (single point)")
            else:
                ax_r.plot(t, vals, ls, marker=marker, ms=3, color=c, mfc=c if sensor == "RS" else "white",
                          label=f"{name} {sensor}")
        if not single:
            ax_r.axvline(t[0], color=c, lw=0.8, ls=(0, (1, 2)))
            ax_r.annotate("set-up", (t[0], 1), xycoords=("data", "axes fraction"), rotation=90, va="top",
                          ha="right", fontsize=6, color=c)
        if has_psnr:
            ax_p = axes[0, 1]
            for key, ls, marker, what in (("psnr_db", "-", "o", "all frames"),
                                          ("psnr_intermediate_db", ":", "x", "intermediate")):
                vals = [r.get(key, np.nan) for r in log]
                if not np.isfinite(vals).any():
                    continue
                if single:
                    ax_p.plot(t, vals, linestyle="none", marker="*" if key == "psnr_db" else "X", ms=12,
                              color=c, mec="black", mew=0.6, label=f"{name} {what} (single point)")
                else:
                    ax_p.plot(t, vals, ls, marker=marker, ms=3, color=c, label=f"{name} {what}")
            if not single:
                ax_p.axvline(t[0], color=c, lw=0.8, ls=(0, (1, 2)))
    if noise_level is not None and math.isfinite(noise_level) and noise_level > 0:
        ax_r.axhline(noise_level, color="0.3", lw=1, ls="-.", label=f"RS noise level ({noise_level:.3g})")
    xlabel = "run time, set-up included (s)"
    ax_r.set(xlabel=xlabel, ylabel="relative data residual", yscale="log", title="data residual")
    ax_r.legend(fontsize=7)
    if has_psnr:
        axes[0, 1].set(xlabel=xlabel, ylabel="PSNR (dB)", title="error against truth")
        axes[0, 1].legend(fontsize=7)
    if one_shot:
        fig.text(0.01, 0.01, f"{', '.join(one_shot)}: {ONE_SHOT_NOTE}; dotted bars: end of each fit's set-up",
                 fontsize=7, color="0.3")
    fig.tight_layout(rect=(0, 0.04 if one_shot else 0, 1, 1))
    if isinstance(png_path, str | os.PathLike):  # a file by name: written beside, renamed into place
        with replacing(Path(png_path)) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    else:
        fig.savefig(png_path, dpi=110, format="png")
    plt.close(fig)


def write_metrics(path: Path, metrics: dict) -> None:
    """metrics.json, written beside and renamed into place: strict JSON, a figure that is not a finite
    number (NaN: nothing to vouch with, e.g. the error visibility of inconsistent data) written as null."""
    write_new(path, json.dumps(finite_or_null(metrics), indent=2, allow_nan=False,
                                default=lambda o: finite_or_null(float(o))))


def finite_or_null(value):
    """`value` (nested dicts, lists and numbers) with every NaN or infinite float replaced by None."""
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value
