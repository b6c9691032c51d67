"""What `rngcam inspect recon.h5` prints: the reconstruction's video, timing, input bundle,
figures and notes, from recon.h5 and the metrics.json beside it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rngcam.errors import RngcamError
from rngcam.formats.bundle import bundle_checksum
from rngcam.recon.report.load import read_metrics, read_recon_h5

FIGURES = (("psnr_db", "PSNR {:.2f} dB"), ("psnr_intermediate_db", "intermediate {:.2f} dB"),
           ("psnr_dynamic_db", "moving region {:.2f} dB"), ("ssim", "SSIM {:.3f}"),
           ("residual_rs", "RS residual {:.4f}"), ("residual_gs", "GS residual {:.4f}"))


def recon_summary(path: str | Path, checksum: bool = False) -> dict:
    """Summary dict of a recon file; RngcamError (one line) when it is not one."""
    path = Path(path)
    h5 = read_recon_h5(path, video=False)
    a = h5["attrs"]
    times = np.asarray(h5["frame_times_s"], np.float64)
    c, k, hh, w = h5["shape"]
    metrics = read_metrics(path.parent)
    bundle = Path(a.get("bundle_path") or "")
    out = {
        "file": str(path), "format": "rngcam-recon", "created_utc": a.get("created_utc", ""),
        "rngcam_version": a.get("rngcam_version", ""), "method": a["settings"].get("method", metrics.get("method")),
        "status": metrics.get("status"), "video_shape_ctyx": [c, k, hh, w],
        "fps": float(a.get("fps", math.nan)), "frame_interval_s": float(a.get("frame_interval_s", math.nan)),
        "frame_times_s": [float(times[0]), float(times[-1])] if times.size else [],
        "frame_times_are": "frame centres, seconds from T0 (the RS trigger)",
        "key_frame_times_s": [float(t) for t in h5.get("key_frame_times_s", [])],
        "bundle_path": str(bundle) if str(bundle) not in ("", ".") else None,
        "bundle_exists": bool(str(bundle) not in ("", ".") and bundle.is_file()),
        "bundle_sha256": a.get("bundle_sha256"), "capture_utc": a.get("capture_utc") or None,
        "rs_noise_level": float(a["rs_noise_level"]) if "rs_noise_level" in a else None,
        "pixel_size_m": float(a["pixel_size_m"]) if "pixel_size_m" in a else None,
        "components": sorted(h5["components"]),
        "left_out": a["left_out"],
        "figures": {key: metrics[key] for key, _ in FIGURES if key in metrics},
        "seconds": metrics.get("seconds"), "iterations": metrics.get("iterations"),
        "notes": metrics.get("notes", []), "events": metrics.get("events", []),
        "warnings": metrics.get("warnings", []),
        "files": sorted(p.name for p in path.parent.iterdir() if p.is_file() and not p.name.startswith(".")),
    }
    if checksum and out["bundle_exists"]:
        try:  # a link or a FIFO at the recorded path: no match, nothing read
            out["bundle_matches"] = bundle_checksum(bundle) == out["bundle_sha256"]
        except RngcamError:
            out["bundle_matches"] = False
    return out


def render_recon_summary(s: dict) -> str:
    """Text form of `recon_summary`."""
    lines = []

    def row(label: str, text: str) -> None:
        lines.append(f"{label:<12} {text}")

    row("file", f"{s['file']}  (an rngcam reconstruction)")
    row("created", f"{s['created_utc'] or '?'}  rngcam {s['rngcam_version'] or '?'}")
    row("method", f"{s['method']}" + (f"  status {s['status']}" if s["status"] else ""))
    c, k, h, w = s["video_shape_ctyx"]
    row("video", f"{k} frames of {w}x{h} px, {c} channel(s) (axes C,T,Y,X; linear intensity, "
        f"1 = the sensor's full scale over its exposure)")
    if s["frame_times_s"]:
        row("time", f"{s['fps']:,.1f} fps, one frame every {s['frame_interval_s'] * 1e6:,.3f} us; frame centres "
            f"{s['frame_times_s'][0] * 1e6:,.1f} to {s['frame_times_s'][1] * 1e6:,.1f} us from the RS trigger")
    if s["key_frame_times_s"]:
        row("key frames", ", ".join(f"{t * 1e6:,.1f}" for t in s["key_frame_times_s"]) + " us (GS mid-exposure)")
    if s["bundle_path"]:
        state = "" if s["bundle_exists"] else "  (not there any more)"
        if "bundle_matches" in s:
            state = "  (sha256 matches)" if s["bundle_matches"] else "  (CHANGED since: sha256 differs)"
        row("bundle", f"{s['bundle_path']}{state}")
    row("sha256", f"{s['bundle_sha256']} (the bundle's)")
    if s["capture_utc"]:
        row("captured", s["capture_utc"])
    figs = [fmt.format(s["figures"][key]) for key, fmt in FIGURES if key in s["figures"]]
    if s["seconds"] is not None:
        figs.append(f"{s['seconds']:.1f} s, {s['iterations']} iteration(s)")
    if figs:
        row("figures", ", ".join(figs))
    if s["rs_noise_level"] is not None:
        row("noise", f"RS relative noise level {s['rs_noise_level']:.4f}")
    if s["pixel_size_m"] is not None:
        row("pixel", f"{s['pixel_size_m'] * 1e6:.3g} um in the scene")
    if s["components"]:
        row("components", ", ".join(s["components"]))
    for x in s["left_out"]:
        row("left out", f"{x[0]} ({x[1]})" if isinstance(x, (list, tuple)) and len(x) == 2 else str(x))
    for label, key in (("note", "notes"), ("event", "events"), ("warning", "warnings")):
        for v in s[key]:
            row(label, v)
    row("files", ", ".join(s["files"]))
    return "\n".join(lines)
