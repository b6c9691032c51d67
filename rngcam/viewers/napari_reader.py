"""napari reader for capture bundles and reconstructions (recon.h5 or its folder), as napari
layer-data tuples: (data, keyword arguments, "image"). napari is not imported here.

Time is the first axis of every layer, in µs from the RS trigger (frame centres), so a
reconstruction, the truth and the GS key frames line up on one time slider; colour is split into
channels (`channel_axis`); a spatial scale is used where recon.h5 knows the pixel size."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

LayerData = tuple[np.ndarray, dict, str]
CHANNEL_NAMES = {3: ["R", "G", "B"], 1: ["intensity"]}
CHANNEL_MAPS = {3: ["red", "green", "blue"], 1: ["gray"]}


def _format(path: Path) -> str:
    from rngcam.h5safe import file_format  # heavy: h5safe loads h5py

    return file_format(path)


def _resolve(path) -> Path | None:
    if isinstance(path, (list, tuple)):
        if len(path) != 1:
            return None
        path = path[0]
    p = Path(path)
    if p.is_dir():
        p = p / "recon.h5"
    return p if p.is_file() and _format(p) in ("rngcam-recon", "rngcam-bundle") else None


def get_reader(path) -> Callable[[object], list[LayerData]] | None:
    """napari's reader hook: a function that reads `path`, or None when it is not an rngcam
    bundle or reconstruction (napari then tries its other readers)."""
    return read if _resolve(path) is not None else None


def read(path) -> list[LayerData]:
    """The layers of an rngcam bundle or reconstruction."""
    p = _resolve(path)
    if p is None:
        raise ValueError(f"{path} is not an rngcam bundle or reconstruction")
    return read_recon(p) if _format(p) == "rngcam-recon" else read_bundle_layers(p)


def _video_layer(video: np.ndarray, times_s: np.ndarray, name: str, px: float, **extra) -> LayerData:
    """(C, T, H, W) on a time axis in µs (frame centres), one layer per channel."""
    c = video.shape[0]
    dt_us = float(np.median(np.diff(times_s)) * 1e6) if len(times_s) > 1 else 1.0
    kw = {"channel_axis": 0, "scale": (dt_us, px, px), "translate": (float(times_s[0]) * 1e6, 0.0, 0.0),
          "name": [f"{name} {n}" for n in CHANNEL_NAMES.get(c, [f"c{i}" for i in range(c)])],
          "colormap": CHANNEL_MAPS.get(c, ["gray"] * c), "blending": "additive", "contrast_limits": (0.0, 1.0),
          "metadata": {"frame_times_s": np.asarray(times_s), "time_unit": "µs from the RS trigger"}, **extra}
    return video, kw, "image"


def _key_layer(frames: np.ndarray, times_s: np.ndarray, all_times_s: np.ndarray | None, px: float,
               name: str) -> LayerData:
    """Key frames (C, G, H, W) at their own times: equally spaced ones as a G-frame layer scaled in
    time; otherwise each held until the next one on the video's frame times."""
    times_s = np.asarray(times_s, np.float64)
    gaps = np.diff(times_s)
    if len(times_s) < 2 or np.allclose(gaps, gaps[0], rtol=0.01) or all_times_s is None:
        layer = _video_layer(frames, times_s, name, px)
    else:
        idx = np.clip(np.searchsorted(times_s, all_times_s, side="right") - 1, 0, len(times_s) - 1)
        layer = _video_layer(frames[:, idx], all_times_s, name, px)
    layer[1]["metadata"]["key_frame_times_s"] = times_s
    layer[1]["opacity"] = 0.8
    return layer


def read_recon(path: Path) -> list[LayerData]:
    """The reconstruction, its GS key frames and RS image (as recon.h5 records them)."""
    # read_recon_h5 checks links, shapes and sizes first
    from rngcam.recon.report.load import read_recon_h5  # heavy: load loads h5py, torch

    h5 = read_recon_h5(path, video=True)
    video, times, attrs = h5["video"], h5["frame_times_s"], h5["attrs"]
    try:
        px = float(attrs.get("pixel_size_m", 0) or 0) * 1e6 or 1.0
    except (TypeError, ValueError):
        px = 1.0
    px = px if np.isfinite(px) and px > 0 else 1.0
    method = str(attrs["settings"].get("method", "recon"))
    layers = [_video_layer(video, times, method, px)]
    if "key_frames" in h5 and "key_frame_times_s" in h5:
        layers.append(_key_layer(h5["key_frames"], h5["key_frame_times_s"], times, px, "GS key frames"))
    if "rs_image" in h5:
        rs = h5["rs_image"]
        rs = rs / max(float(np.percentile(rs, 99.5)), 1e-12)
        layers.append(_video_layer(rs[:, None], times[:1], "RS image (coded)", px, visible=False))
    return layers


def json_method(settings) -> str:
    try:
        return str(json.loads(settings).get("method", "recon"))
    except (ValueError, AttributeError):
        return "recon"


def _raw_to_cthw(frames: np.ndarray, bit_depth: int, black: float) -> np.ndarray:
    """Raw (N, H, W[, C]) DN -> (C, N, H, W) float32, 0 = black level, 1 = full scale."""
    x = np.asarray(frames, np.float32)
    x = x[..., None] if x.ndim == 3 else x
    return np.moveaxis((x - black) / float(2**bit_depth - 1 - black), -1, 0)


def read_bundle_layers(path: Path) -> list[LayerData]:
    """A capture bundle: the truth (simulated bundles), the GS key frames at their mid-exposure
    times and the RS frame, raw frames scaled to 0..1 of full scale above black."""
    from rngcam.formats.bundle import open_bundle  # heavy: bundle loads h5py, torch

    layers = []
    with open_bundle(path) as b:
        truth_times = None
        if b.truth is not None:
            truth_times = np.asarray(b.truth.frame_times_s, np.float64)
            layers.append(_video_layer(np.asarray(b.truth.video, np.float32), truth_times, "truth", 1.0))
        if b.gs is not None and len(b.gs.frames):
            gs = _raw_to_cthw(b.gs.frames[()], b.gs.bit_depth, b.gs.black_level_dn)
            mid = np.asarray(b.gs.trigger_times_s, np.float64) + b.gs.exposure_s / 2
            layers.append(_key_layer(gs, mid, truth_times, 1.0, "GS key frames"))
        if b.rs is not None and len(b.rs.frames):
            rs = _raw_to_cthw(b.rs.frames[()][:1], b.rs.bit_depth, b.rs.black_level_dn)
            layers.append(_video_layer(rs, np.zeros(1), "RS frame (raw, coded)", 1.0))
    return layers
