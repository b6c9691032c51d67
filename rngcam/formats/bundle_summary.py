"""What `rngcam inspect` shows of a bundle: a JSON-able summary and its text form."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from rngcam import pixels
from rngcam.formats.bundle_read import bundle_checksum, open_checked
from rngcam.formats.bundle_schema import (
    SCHEMA_VERSION,
    Bundle,
    Calibration,
    CameraRecord,
    check_bundle,
    declared_cameras,
    gs_start_offsets,
    trigger_faults,
)


def _camera_summary(rec: CameraRecord) -> dict:
    trig = np.asarray(rec.trigger_times_s, dtype=np.float64)
    out = {
        "model": rec.model,
        "serial": rec.serial,
        "frames": int(np.shape(rec.frames)[0]),
        "shape": list(np.shape(rec.frames)),
        "dtype": str(rec.frames.dtype),
        "pixel_format": rec.pixel_format,
        "bit_depth": int(rec.bit_depth),
        "black_level_dn": float(rec.black_level_dn),
        "gain_db": float(rec.gain_db),
        "exposure_ms": float(rec.exposure_s) * 1e3,
        "trigger_times_ms": [float(t) * 1e3 for t in trig],
        "features": len(rec.features),
    }
    if rec.line_time_s is not None:
        out["line_time_us"] = float(rec.line_time_s) * 1e6
        out["readout"] = rec.readout
    if rec.exposure_start_s is not None:
        out["exposure_start_ms"] = [float(t) * 1e3 for t in np.asarray(rec.exposure_start_s, np.float64)]
        out["exposure_start_method"] = rec.exposure_start_method
    return out


def _start_offsets(gs: CameraRecord | None) -> dict | None:
    """The GS frames' measured exposure starts against the plan (us), and the tolerance."""
    found = gs_start_offsets(gs)
    if found is None:
        return None
    offsets, tol = found
    return {"offsets_us": [float(o) * 1e6 for o in offsets], "tolerance_us": tol * 1e6,
            "beyond_tolerance": [int(i) + 1 for i in np.flatnonzero(np.abs(offsets) > tol)]}


def summary_dict(bundle: Bundle, path: str | os.PathLike | None = None,
                 problems: list[str] | None = None,
                 stats: dict[str, list[pixels.FrameStats]] | None = None) -> dict:
    """The facts `summarise` prints, as a JSON-able dict (times in ms/us for reading); with
    `stats` (pixel_stats), each frame's saturated and dark fractions under 'pixels'."""
    from rngcam.physics.psf import spectral_support  # heavy: psf loads cv2

    out: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        out["file"] = str(p)
        if p.is_file():
            out["size_bytes"] = p.stat().st_size
    out["created_utc"] = bundle.created_utc
    out["rngcam_version"] = bundle.rngcam_version
    out["schema_version"] = SCHEMA_VERSION
    out["cameras"] = list(declared_cameras(bundle.meta))
    for name in ("rs", "gs"):
        rec = getattr(bundle, name)
        out[name] = _camera_summary(rec) if rec is not None else None
    out["gs_start_offsets"] = _start_offsets(bundle.gs)
    cal = bundle.calibration or Calibration()
    psf = None
    if cal.psf is not None:
        arr = np.asarray(cal.psf)
        psf = {"shape": list(arr.shape), "source": cal.psf_source, "bias": float(cal.psf_bias),
               "spectral_support": spectral_support(arr) if np.all(np.isfinite(arr)) else None}
    out["calibration"] = {
        "psf": psf,
        "gs_to_rs": np.asarray(cal.gs_to_rs).tolist() if cal.gs_to_rs is not None else None,
        "white_balance": (np.asarray(cal.white_balance).tolist()
                          if cal.white_balance is not None else None),
        "field_stop_open_fraction": (float(np.mean(cal.field_stop))
                                     if cal.field_stop is not None else None),
        "sources": dict(cal.extra.get("sources") or {}),  # which of rig / calibration / mock gave each value
    }
    out["trigger"] = ({"generator": bundle.trigger.generator, "settings": bundle.trigger.settings,
                       "errors": list(bundle.trigger.errors)} if bundle.trigger else None)
    if bundle.truth is not None:
        shape = list(np.shape(bundle.truth.video))
        dt = float(bundle.truth.dt_s)
        out["truth"] = {"shape_cthw": shape, "dt_us": dt * 1e6,
                        "fps": 1.0 / dt if dt > 0 else None}
    else:
        out["truth"] = None
    out["meta"] = bundle.meta
    if stats is not None:
        out["pixels"] = {name: [{"saturated_fraction": st.saturated, "dark_fraction": st.dark,
                                 "max_dn": st.max_dn} for st in frames] for name, frames in stats.items()}
    out["problems"] = list(problems) if problems is not None else check_bundle(bundle)
    return out


SOURCE_LABELS = {"line_time_s": "line time", "psf": "PSF", "gs_to_rs": "alignment",
                 "white_balance": "white bal.", "rs_black_level_dn": "RS black", "gs_black_level_dn": "GS black"}


def _fmt_ms(values: list[float], limit: int = 8) -> str:
    shown = ", ".join(f"{v:.3f}" for v in values[:limit])
    return shown + (f", ... ({len(values)} in all)" if len(values) > limit else "")


def render_summary(s: dict) -> str:
    """Text form of a `summary_dict` (plus its 'sha256' entry when present)."""
    lines = []

    def row(label: str, text: str) -> None:
        lines.append(f"{label:<12} {text}")

    if "file" in s:
        size = f"  ({s['size_bytes'] / 1e6:.1f} MB)" if "size_bytes" in s else ""
        row("file", s["file"] + size)
    row("created", f"{s['created_utc'] or '?'}  rngcam {s['rngcam_version'] or '?'}  "
        f"schema {s['schema_version']}")
    for name in ("rs", "gs"):
        cam = s[name]
        label = f"{name.upper()} camera"
        if cam is None:
            row(label, "none (an RS-only bundle)" if name == "gs" and s.get("cameras") == ["rs"] else "missing")
            continue
        ident = " ".join(x for x in (cam["model"], f"serial {cam['serial']}" if cam["serial"] else "")
                         if x) or "(model unknown)"
        row(label, ident)
        row("", f"{cam['frames']} frame(s) {tuple(cam['shape'])} {cam['dtype']}  "
            f"{cam['pixel_format']} {cam['bit_depth']}-bit  black {cam['black_level_dn']:g} DN  "
            f"gain {cam['gain_db']:g} dB")
        timing = f"exposure {cam['exposure_ms']:.3f} ms"
        if "line_time_us" in cam:
            timing += f"  line time {cam['line_time_us']:.3f} us, readout {cam.get('readout', 'top-down')}"
        row("", timing + f"  trigger times {_fmt_ms(cam['trigger_times_ms'])} ms")
        if "exposure_start_ms" in cam:
            row("", f"measured exposure starts {_fmt_ms(cam['exposure_start_ms'])} ms "
                f"({cam['exposure_start_method'] or 'method not recorded'})")
    starts = s.get("gs_start_offsets")
    if starts:
        shown = ", ".join(f"{o:+.1f}" for o in starts["offsets_us"][:8])
        beyond = starts["beyond_tolerance"]
        row("GS starts", f"{shown} us against the plan (tolerance +-{starts['tolerance_us']:.1f} us): "
            + (f"frame(s) {', '.join(map(str, beyond))} beyond it" if beyond else "all within"))
    cal = s["calibration"]
    psf = cal["psf"]
    if psf:
        support = (f"  spectral support {100 * psf['spectral_support']:.2f} % of frequencies "
                   "> 10 % of DC" if psf["spectral_support"] is not None else "")
        source = f" from {psf['source']}" if psf["source"] else ""
        row("PSF", f"{tuple(psf['shape'])}{source}  bias {psf['bias']:g}{support}")
    else:
        row("PSF", "none")
    row("alignment", "3x3 GS-to-RS homography" if cal["gs_to_rs"] is not None else "none")
    wb = cal["white_balance"]
    row("white bal.", " ".join(f"{v:.4g}" for v in wb) if wb is not None else "none")
    fs = cal["field_stop_open_fraction"]
    row("field stop", f"{100 * fs:.1f} % of pixels open" if fs is not None else "none")
    if cal.get("sources"):
        row("from", ", ".join(f"{SOURCE_LABELS.get(k, k)} {v}" for k, v in cal["sources"].items()))
    trig = s["trigger"]
    if trig:
        real = trigger_faults(trig["errors"])
        row("trigger", f"{trig['generator']}  "
            + (f"{len(real)} error(s) read back" if real else "no errors read back"))
    else:
        row("trigger", "none recorded")
    truth = s["truth"]
    if truth:
        c, t, h, w = (truth["shape_cthw"] + [None] * 4)[:4]
        fps = f" -> {truth['fps']:.1f} fps" if truth["fps"] else ""
        row("truth", f"C={c} T={t} H={h} W={w}  dt {truth['dt_us']:.3f} us{fps}")
    else:
        row("truth", "none")
    if s["meta"]:
        row("meta", ", ".join(f"{k}={v}" for k, v in s["meta"].items()))
    for name, frames in s.get("pixels", {}).items():
        for i, st in enumerate(frames):
            label = name.upper() if len(frames) == 1 else f"{name.upper()} frame {i + 1}"
            row("pixels" if i == 0 else "", f"{label}: {100 * st['saturated_fraction']:.2f} % saturated, "
                f"{100 * st['dark_fraction']:.2f} % at or below black, max {st['max_dn']:,.0f} DN")
    if "recon" in s:
        r = s["recon"]
        need = ", ".join(f"{m} ~{b / 2**30:,.2f} GiB" for m, b in r["memory_bytes"].items())
        row("recon", f"bin {r['bin']}: {r['frames']:,} frames of {r['height']}x{r['width']}x{r['channels']} "
            f"at {r['fps']:,.0f} fps; {need} (limit {r['max_memory_bytes'] / 2**30:,.1f} GiB)")
    for p in s["problems"]:
        row("problem", p)
    if "sha256" in s:
        row("sha256", s["sha256"])
    return "\n".join(lines)


def summarise(bundle: Bundle, path: str | os.PathLike | None = None,
              problems: list[str] | None = None) -> str:
    """Human summary of a bundle (what `rngcam inspect` prints)."""
    return render_summary(summary_dict(bundle, path, problems))


def inspect_bundle(path: str | os.PathLike, checksum: bool = False) -> dict:
    """Summary dict of a bundle file, frames left on disk; BundleError if it is unusable.

    Warning-level problems are listed under 'problems'; with `checksum`, adds 'sha256'.
    """
    path = Path(path)
    with open_checked(path) as (bundle, problems, stats):
        summary = summary_dict(bundle, path, problems, stats)
    if checksum:
        summary["sha256"] = bundle_checksum(path)
    return summary
