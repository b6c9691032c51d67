"""`rngcam export`: a bundle (or a reconstruction's video) to TIFF files with ImageJ metadata and
the sidecar `rngcam import` reads, so that importing an export gives the bundle back.

A bundle becomes rs.tif, gs.tif (when it has GS frames), psf.tif, truth.tif (when it has a
truth), field_stop.tif (when it has one) and capture.yaml beside them; timestamps, frame
counters and the trigger generator's record are not carried (nothing reconstructs from them).
Frames keep their dtype (ImageJ metadata where ImageJ reads the dtype: uint8, uint16, float32);
the truth and a reconstruction are float32 ImageJ hyperstacks (T, C, Y, X) with their frame
interval in seconds.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import yaml

from rngcam.errors import RngcamError
from rngcam.formats.bundle_schema import Bundle
from rngcam.untrusted import replacing, write_new

SIDECAR_NAME = "capture.yaml"
_IMAGEJ_DTYPES = ("uint8", "uint16", "float32")
HEADER = ("# rngcam import sidecar written by `rngcam export`: the capture's timing, sensors and calibration\n"
          "# (rngcam import --template explains every field). Import it back with: rngcam import {name} -o OUT.h5\n")


def _tiff(path: Path, planes: np.ndarray, axes: str, frame_interval_s: float | None = None,
          overwrite: bool = True) -> None:
    """`planes` to `path`: an ImageJ hyperstack with `axes` (e.g. TYX, TCYX) where ImageJ reads
    the dtype, else a plain TIFF whose axes tifffile records."""
    import tifffile  # heavy: tifffile

    planes = np.ascontiguousarray(planes)
    imagej = planes.dtype.name in _IMAGEJ_DTYPES
    meta: dict = {"axes": axes}
    if imagej:
        if "C" in axes:
            meta["mode"] = "composite" if planes.shape[axes.index("C")] > 1 else "grayscale"
        if frame_interval_s is not None and math.isfinite(frame_interval_s) and frame_interval_s > 0:
            meta.update(finterval=float(frame_interval_s), tunit="s")
    with replacing(path, replace=overwrite) as tmp:
        tifffile.imwrite(tmp, planes, imagej=imagej, metadata=meta, photometric="minisblack")


def _camera_planes(frames: np.ndarray) -> tuple[np.ndarray, str]:
    """(N, H, W) -> TYX; (N, H, W, C) -> TCYX (ImageJ keeps channels as planes)."""
    frames = np.asarray(frames)
    if frames.ndim == 4:
        return np.moveaxis(frames, -1, 1), "TCYX"
    return frames, "TYX"


def _interval(times: np.ndarray) -> float | None:
    """The frame interval of evenly spaced `times`, else None."""
    times = np.asarray(times, np.float64)
    if times.size < 2:
        return None
    steps = np.diff(times)
    return float(steps.mean()) if np.allclose(steps, steps.mean(), rtol=1e-9, atol=0) else None


def _camera_part(rec, name: str, simulated: bool) -> dict:
    part = {"file": f"{name}.tif", "pixel_format": rec.pixel_format, "bit_depth": int(rec.bit_depth),
            "black_level_dn": float(rec.black_level_dn),
            "exposure_s": float(rec.exposure_s), "gain_db": float(rec.gain_db), "model": rec.model,
            "serial": rec.serial}
    features = {k: v for k, v in rec.features.items()
                if k not in ("readout", "first_row_offset_s", "line_time_source")}
    part.update(binning=int(features.pop("binning", 1) or 1), pixel_pitch_um=features.pop("pixel_pitch_um", None))
    features.pop("bayer_pattern", None)  # the frames are stored as RGGB: that is what they are now
    if name == "rs":
        part.update(line_time_s=float(rec.line_time_s),
                    line_time_source=rec.features.get("line_time_source", "simulated" if simulated else "other"),
                    readout=getattr(rec, "readout", "top-down"), first_row_offset_s=0.0)
    else:
        part["frame_times_s"] = [float(t) for t in np.asarray(rec.trigger_times_s, np.float64)]
    if rec.exposure_start_s is not None:
        part["measured_starts_s"] = [float(t) for t in np.asarray(rec.exposure_start_s, np.float64)]
        part["measured_starts_method"] = rec.exposure_start_method
    part["features"] = json.loads(json.dumps(features, default=_plain))
    return part


def _plain(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def sidecar_dict(bundle: Bundle) -> dict:
    """The sidecar that describes `bundle` with the files `export_bundle` writes."""
    imported = bundle.meta.get("import")
    origin = imported.get("exported_from", "") if isinstance(imported, dict) else ""
    simulated = any(str(s).startswith("rngcam simulate") for s in (bundle.meta.get("source", ""), origin))
    cal = bundle.calibration
    side: dict = {"description": str(bundle.meta.get("description", "") or f"exported {bundle.meta.get('source', '')}"),
                  "rs": _camera_part(bundle.rs, "rs", simulated)}
    if bundle.gs is not None:
        side["gs"] = _camera_part(bundle.gs, "gs", simulated)
    side["psf"] = {"file": "psf.tif", "axes": "CHW", "bias": 0.0, "subtracted_bias": float(cal.psf_bias),
                   "binning": side["rs"]["binning"], "source": cal.psf_source}
    side["calibration"] = {
        "gs_to_rs": None if cal.gs_to_rs is None else np.asarray(cal.gs_to_rs, np.float64).tolist(),
        "white_balance": None if cal.white_balance is None else [float(g) for g in cal.white_balance],
        "source": "", "extra": json.loads(json.dumps(cal.extra, default=_plain))}
    if cal.field_stop is not None:
        side["calibration"]["field_stop_file"] = "field_stop.tif"
    if bundle.truth is not None:
        times = np.asarray(bundle.truth.frame_times_s, np.float64)
        side["truth"] = {"file": "truth.tif", "dt_s": float(bundle.truth.dt_s),
                         "start_s": float(times[0]) if times.size else 0.0}
    meta = {k: v for k, v in bundle.meta.items() if k not in ("import", "cameras", "description")}
    if origin:
        meta["source"] = origin
    side["meta"] = json.loads(json.dumps(meta, default=_plain))
    side["rig_yaml"] = bundle.rig_yaml
    return side


def export_bundle(bundle: Bundle, folder: Path | str, overwrite: bool = False) -> list[Path]:
    """Write `bundle` as TIFF files and capture.yaml into `folder` (made if missing); the paths written.
    Without `overwrite`, an existing file of the export is refused (one line) before anything is written."""
    folder = Path(folder)
    names = ["rs.tif", "psf.tif", SIDECAR_NAME] + (["gs.tif"] if bundle.gs is not None else []) \
        + (["truth.tif"] if bundle.truth is not None else []) \
        + (["field_stop.tif"] if bundle.calibration.field_stop is not None else [])
    if not overwrite:
        taken = [n for n in names if (folder / n).exists() or (folder / n).is_symlink()]
        if taken:
            raise RngcamError(f"{folder / taken[0]} exists (pass --overwrite to replace the export)")
    if folder.exists() and not folder.is_dir():
        raise RngcamError(f"{folder} is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, rec in (("rs", bundle.rs), ("gs", bundle.gs)):
        if rec is not None:
            planes, axes = _camera_planes(np.asarray(rec.frames))
            step = _interval(rec.trigger_times_s) if name == "gs" else None
            _tiff(folder / f"{name}.tif", planes, axes, step)
            written.append(folder / f"{name}.tif")
    _tiff(folder / "psf.tif", np.asarray(bundle.calibration.psf, np.float32), "CYX")
    written.append(folder / "psf.tif")
    if bundle.calibration.field_stop is not None:
        _tiff(folder / "field_stop.tif", np.asarray(bundle.calibration.field_stop, np.uint8), "YX")
        written.append(folder / "field_stop.tif")
    if bundle.truth is not None:
        video = np.asarray(bundle.truth.video, np.float32)
        _tiff(folder / "truth.tif", np.moveaxis(video, 0, 1), "TCYX", float(bundle.truth.dt_s))
        written.append(folder / "truth.tif")
    text = HEADER.format(name=SIDECAR_NAME) + yaml.safe_dump(sidecar_dict(bundle), sort_keys=False, width=100)
    write_new(folder / SIDECAR_NAME, text)
    written.append(folder / SIDECAR_NAME)
    return written


def export_video(video, frame_times_s: np.ndarray, path: Path | str, about: dict,
                 overwrite: bool = False) -> list[Path]:
    """A reconstruction's video (C, T, H, W) to a float32 ImageJ hyperstack at `path` with its frame
    interval, and a YAML sidecar beside it (PATH.yaml: frame times, interval, units, `about`)."""
    path = Path(path)
    side = path.with_suffix(".yaml")
    if not overwrite:
        for p in (path, side):
            if p.exists() or p.is_symlink():
                raise RngcamError(f"{p} exists (pass --overwrite to replace it)")
    times = np.asarray(frame_times_s, np.float64)
    step = _interval(times)
    video = np.asarray(video, np.float32)
    _tiff(path, np.moveaxis(video, 0, 1), "TCYX", step, overwrite=True)
    record = {"file": path.name, "axes": "TCYX", "intensity": "linear, float32 (the reconstruction's units)",
              "frame_interval_s": step, "time_unit": "s", "frame_times_s": [float(t) for t in times],
              **json.loads(json.dumps(about, default=_plain))}
    write_new(side, "# rngcam export: a reconstruction's video and its timing\n"
              + yaml.safe_dump(record, sort_keys=False, width=100))
    return [path, side]
