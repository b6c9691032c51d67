"""The calibration file: one HDF5 per rig holding what `rngcam calibrate` measured.

Where: the rig names it (`calibration.file`, relative to the rig file); without that, it lives
beside the rig file as `<rig file name without .yaml>.calib.h5` (rigs/lab.yaml ->
rigs/lab.calib.h5): `rngcam calibrate` writes there (or to `-o FILE`) and a capture finds it
there. Before a capture, rngcam.acquire.resolve merges what the file holds with the rig (the
file's values replace the rig's inline ones) and the bundle records which came from where.

Layout (every part optional; each subcommand replaces only its own part, the others stay):

- root attrs: ``format`` = "rngcam-calibration", ``schema_version``, ``rig_name``,
  ``updated_utc``.
- ``psf`` (C, H, W) float32, sums to 1 per channel, on the RS sensor grid (Bayer sensors: after
  2x2 binning per colour). rngcam.physics.psf.load_psf reads it, so a rig's
  ``calibration.psf.path`` may point straight at this file.
- ``line_time_s`` scalar float64; its attrs ``method_key`` ("flicker": measured from an LED,
  "readout": the rough SensorReadoutTime slope) and ``uncertainty_s`` (1 sigma, flicker only).
- ``gs_to_rs`` (3, 3) float64: raw GS pixel -> raw RS sensor pixel.
- ``white_balance`` (C,) float64: multiplies GS measurements to the RS scale (recon's Lambda).

Each dataset's attrs are its provenance: ``created_utc``, ``method`` and the numbers that
qualify it (frames, dark, SNR; heights and readout times; residual, ECC, model ...), as
scalars or JSON text.

Writes are atomic: the whole file is written under a temporary name and renamed.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from rngcam import h5safe
from rngcam.errors import ConfigError, RngcamError
from rngcam.untrusted import printable, temp_beside

FORMAT_NAME = "rngcam-calibration"
SCHEMA_VERSION = 1
PARTS = ("psf", "line_time_s", "gs_to_rs", "white_balance")
LINE_TIME_METHODS = ("flicker", "readout")
_PART_ELEMENTS = {"psf": h5safe.MAX_CHANNELS * h5safe.MAX_SIDE**2, "line_time_s": 1, "gs_to_rs": 9,
                  "white_balance": h5safe.MAX_CHANNELS}


class CalibrationFileError(RngcamError):
    """A calibration file is missing, unreadable or inconsistent."""


@dataclass
class StoredCalibration:
    """What a calibration file holds; `provenance[part]` is that part's attributes."""

    psf: np.ndarray | None = None
    line_time_s: float | None = None
    gs_to_rs: np.ndarray | None = None
    white_balance: np.ndarray | None = None
    rig_name: str = ""
    provenance: dict[str, dict] = field(default_factory=dict)

    def parts(self) -> list[str]:
        return [p for p in PARTS if getattr(self, p) is not None]

    @property
    def line_time_method(self) -> str | None:
        """"flicker" or "readout" (how line_time_s was found), None when not recorded."""
        v = self.provenance.get("line_time_s", {}).get("method_key")
        return v if v in LINE_TIME_METHODS else None

    @property
    def line_time_uncertainty_s(self) -> float | None:
        """The line time's 1-sigma uncertainty (s), when recorded and sane."""
        v = self.provenance.get("line_time_s", {}).get("uncertainty_s")
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v >= 0
        return float(v) if ok else None


def now_utc() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _attr_value(v):
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v)
    if v is None:
        return "null"
    return v


def _read_attrs(obj) -> dict:
    out = {}
    for k, v in obj.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        if isinstance(v, str) and v[:1] in "[{":
            try:
                v = json.loads(v)
            except ValueError:
                pass
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


def read_calibration(path: str | Path) -> StoredCalibration:
    """Read a calibration file; CalibrationFileError (one line) when it is not one."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: calibration file not found (run `rngcam calibrate`)")
    try:
        with h5safe.open_untrusted(path, "calibration file") as f:
            for name in f.attrs:
                h5safe.check_attr(f, name)
            if f.attrs.get("format") != FORMAT_NAME:
                raise CalibrationFileError(f"{path}: not an rngcam calibration file")
            version = f.attrs.get("schema_version", -1)
            if np.ndim(version) != 0 or np.asarray(version).dtype.kind not in "ui" or int(version) != SCHEMA_VERSION:
                raise CalibrationFileError(f"{path}: calibration schema version "
                                           f"{printable(version, 40)} (this rngcam reads {SCHEMA_VERSION})")
            out = StoredCalibration(rig_name=printable(f.attrs.get("rig_name", ""), 200))
            for part in PARTS:
                if part in f:
                    value = h5safe.read_small(f, part, _PART_ELEMENTS[part], "uif")
                    value = float(value) if part == "line_time_s" else np.asarray(value, np.float64)
                    setattr(out, part, value)
                    for name in f[part].attrs:
                        h5safe.check_attr(f[part], name)
                    out.provenance[part] = _read_attrs(f[part])
    except CalibrationFileError:
        raise
    except RngcamError as exc:
        raise CalibrationFileError(f"{path}: {exc}" if str(path) not in str(exc) else str(exc)) from None
    except (OSError, RuntimeError, KeyError, ValueError, TypeError, OverflowError, RecursionError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CalibrationFileError(f"{path}: cannot read calibration file ({printable(reason, 200)})") from None
    _validate(out, path)
    return out


def _validate(cal: StoredCalibration, path: Path) -> None:
    def bad(msg):
        raise CalibrationFileError(f"{path}: {msg}")

    if cal.psf is not None and (cal.psf.ndim != 3 or not np.all(np.isfinite(cal.psf))
                                or np.any(cal.psf.sum(axis=(1, 2)) <= 0)):
        bad(f"psf must be a finite (C, H, W) array with signal in every channel, got shape {cal.psf.shape}")
    if cal.line_time_s is not None and not (np.isfinite(cal.line_time_s) and cal.line_time_s > 0):
        bad(f"line_time_s must be finite and > 0, got {cal.line_time_s}")
    if cal.gs_to_rs is not None and (cal.gs_to_rs.shape != (3, 3) or not np.all(np.isfinite(cal.gs_to_rs))):
        bad(f"gs_to_rs must be a finite 3x3 matrix, got shape {cal.gs_to_rs.shape}")
    if cal.white_balance is not None:
        wb = cal.white_balance
        if wb.ndim != 1 or not np.all(np.isfinite(wb)) or np.any(wb <= 0):
            bad(f"white_balance must be finite, positive and (C,), got {wb.tolist()}")


def update_calibration(path: str | Path, rig_name: str = "", **parts) -> StoredCalibration:
    """Replace the given parts (name=(value, provenance dict)) in the file, keeping the others.
    Creates the file when absent; writes atomically."""
    path = Path(path)
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise ValueError(f"unknown calibration part(s): {sorted(unknown)}")
    current = read_calibration(path) if path.exists() else StoredCalibration()
    for name, (value, provenance) in parts.items():
        setattr(current, name, float(value) if name == "line_time_s" else np.asarray(value, np.float64))
        current.provenance[name] = {"created_utc": now_utc(), **provenance}
    current.rig_name = rig_name or current.rig_name
    _validate(current, path)
    if not path.parent.is_dir():
        raise CalibrationFileError(f"cannot write {path}: directory {path.parent} does not exist")
    tmp = temp_beside(path)  # unique, created O_EXCL: a planted link at a fixed name is never followed
    try:
        with h5py.File(tmp, "w") as f:
            for name in current.parts():
                value = getattr(current, name)
                dtype = np.float32 if name == "psf" else np.float64
                ds = f.create_dataset(name, data=np.asarray(value, dtype=dtype))
                for k, v in current.provenance.get(name, {}).items():
                    ds.attrs[k] = _attr_value(v)
            f.attrs["rig_name"] = current.rig_name
            f.attrs["updated_utc"] = now_utc()
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["format"] = FORMAT_NAME
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return read_calibration(path)


def beside_rig(rig) -> Path:
    """The calibration file the rule puts beside the rig file: rigs/lab.yaml -> rigs/lab.calib.h5
    (a rig parsed from text, with no file, uses `<rig name>.calib.h5` in the current folder)."""
    if rig.path.suffix in (".yaml", ".yml") and rig.path.parent.is_dir():
        return rig.path.with_suffix(".calib.h5")
    return Path(f"{rig.config.name}.calib.h5")


def calibration_path(rig, override: str | Path | None = None) -> Path:
    """Where `rngcam calibrate` writes: `override`, else the rig's calibration.file, else
    beside the rig file (`beside_rig`), where a capture finds it."""
    if override is not None:
        return Path(override)
    named = getattr(rig.config.calibration, "file", None)
    if named:
        return rig.resolve(named)
    return beside_rig(rig)


def rig_calibration(rig, missing_ok: bool = False) -> tuple[StoredCalibration | None, Path | None]:
    """The rig's calibration file, read: the one it names, else the one beside it (`beside_rig`)
    if present; (None, None) when there is none. A named file that does not exist is a
    ConfigError (a capture would otherwise silently use the rig's inline values), unless
    `missing_ok` (calibrate is about to create it)."""
    named = getattr(rig.config.calibration, "file", None)
    if not named:
        path = beside_rig(rig)
        return (read_calibration(path), path) if path.is_file() else (None, None)
    path = rig.resolve(named)
    if missing_ok and not path.exists():
        return None, path
    if not path.is_file():
        raise ConfigError(f"{rig.path}: calibration.file: {path} not found (run `rngcam calibrate "
                          f"... --rig {rig.path}` first, or remove the entry)")
    return read_calibration(path), path


def is_calibration_file(path: str | Path) -> bool:
    """True when `path` is an HDF5 file whose `format` attribute says rngcam-calibration."""
    return h5safe.file_format(path) == FORMAT_NAME


def calibration_summary(path: str | Path) -> dict:
    """What `rngcam inspect CAL.h5` shows: the parts, the line time with its method and
    uncertainty, the other parts' shapes, and each part's provenance."""
    cal = read_calibration(path)
    out = {"file": str(path), "format": FORMAT_NAME, "rig_name": cal.rig_name, "parts": cal.parts(),
           "line_time_s": cal.line_time_s, "line_time_uncertainty_s": cal.line_time_uncertainty_s,
           "line_time_method": cal.line_time_method}
    for name in ("psf", "gs_to_rs", "white_balance"):
        value = getattr(cal, name)
        out[name] = None if value is None else (list(value.shape) if name == "psf" else value.tolist())
    out["provenance"] = {k: cal.provenance[k] for k in cal.parts() if k in cal.provenance}
    return out
