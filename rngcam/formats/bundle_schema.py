"""The HDF5 capture bundle (schema v1): its records and their validation.

A bundle is the contract between acquisition, simulation and reconstruction. Layout:

- root attrs: ``format``, ``schema_version``, ``created_utc``, ``rngcam_version``,
  ``rig_yaml`` (verbatim), ``meta`` (JSON).
- ``rs`` / ``gs`` groups (both required, but for an RS-only bundle, whose ``meta`` says
  ``"cameras": ["rs"]``, without ``gs``): dataset ``frames`` (native dtype, one chunk per
  frame), ``trigger_times_s`` and optional ``timestamps_s`` (float64), ``frame_ids`` (int64),
  ``exposure_start_s`` (float64, measured exposure starts, attr ``method``);
  attrs ``pixel_format``, ``bit_depth``, ``black_level_dn``, ``exposure_s``, ``gain_db``,
  ``model``, ``serial``, optional ``line_time_s`` and ``readout`` (RS; absent: top-down,
  physics.timing.READOUTS), ``features`` (JSON).
- ``calibration`` group: optional datasets ``psf`` (C, Hp, Wp) float32, ``gs_to_rs`` (3, 3),
  ``white_balance`` (C,), ``field_stop`` (H, W) bool; attrs ``psf_source``, ``psf_bias``,
  ``extra`` (JSON).
- optional ``trigger`` group: attrs ``generator``, ``settings`` and ``errors`` (JSON).
- optional ``truth`` group: ``video`` (C, T, H, W) float32, ``frame_times_s`` (T,), attr ``dt_s``.

Text attributes are fixed-length UTF-8 and every dataset carries a Fletcher-32 checksum, so a
damaged file is reported rather than misread. The ``format`` attribute is written last and the
file is written under a temporary name, renamed only when complete, so an interrupted write
never leaves a file that reads as a bundle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from rngcam.physics.timing import DEFAULT_READOUT, READOUTS, readout_lines
from rngcam.untrusted import printable

SCHEMA_VERSION = 1
FORMAT_NAME = "rngcam-bundle"
WARNING_PREFIX = "warning: "
COMPRESSIONS = (None, "lzf", "gzip")
PSF_SIZE_RATIO = 2  # a PSF side at most this many times the RS frame's (light spread past it never lands)


def short(value) -> str:
    """A field's value for a repr: arrays (and long texts) by their shape, not their contents."""
    if isinstance(value, np.ndarray) or hasattr(value, "shape") and hasattr(value, "dtype"):
        return f"array({tuple(value.shape)}, {value.dtype})"
    if isinstance(value, ShortRepr):
        return repr(value)
    text = repr(value)
    return text if len(text) <= 80 else text[:60] + f"... ({len(text)} characters)"


class ShortRepr:
    """A dataclass whose repr shows arrays by their shape: a bundle prints in a few lines, not
    its pixels."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(" + ", ".join(f"{f.name}={short(getattr(self, f.name))}"
                                                     for f in fields(self)) + ")"


@dataclass(repr=False)
class CameraRecord(ShortRepr):
    """One camera's capture: raw frames in their native dtype plus how they were taken.

    frames: (N, H, W) raw mosaic/mono or (N, H, W, C) colour (uint8/uint16/float32 ...).
    trigger_times_s: (N,) trigger time of each frame relative to T0 (the RS trigger, 0).
    line_time_s: RS row-to-row delay (required for the RS camera, None for GS).
    timestamps_s / frame_ids: (N,) device timestamps (s) and frame counters, when known.
    exposure_start_s: (N,) measured exposure starts, seconds on the RS trigger's timeline (the
    planned ones are trigger_times_s), when the cameras report them (rngcam.acquire.exposure_clock);
    exposure_start_method says how they were measured.
    features: every feature read back from the camera (JSON-able).
    readout: the RS sensor's readout order (physics.timing.READOUTS; "top-down" when not recorded).
    """

    frames: np.ndarray
    pixel_format: str
    bit_depth: int
    black_level_dn: float
    exposure_s: float
    trigger_times_s: np.ndarray
    line_time_s: float | None = None
    gain_db: float = 0.0
    model: str = ""
    serial: str = ""
    timestamps_s: np.ndarray | None = None
    frame_ids: np.ndarray | None = None
    features: dict = field(default_factory=dict)
    exposure_start_s: np.ndarray | None = None
    exposure_start_method: str = ""
    readout: str = DEFAULT_READOUT


@dataclass(repr=False)
class Calibration(ShortRepr):
    """Optical calibration, every part optional.

    psf: (C, Hp, Wp) float32, bias-subtracted, on the RS sensor's pixel grid.
    gs_to_rs: (3, 3) homography mapping GS pixel (x, y, 1) to RS sensor pixel.
    white_balance: (C,) per-channel GS/RS gain (start value for Lambda).
    field_stop: (H, W) bool on the RS sensor grid (True = light reaches the pixel).
    """

    psf: np.ndarray | None = None
    psf_source: str = ""
    psf_bias: float = 0.0
    gs_to_rs: np.ndarray | None = None
    white_balance: np.ndarray | None = None
    field_stop: np.ndarray | None = None
    extra: dict = field(default_factory=dict)


@dataclass(repr=False)
class TriggerRecord(ShortRepr):
    """The trigger generator: identity (*IDN? or "fake"/"mock"), settings sent, SYST:ERR? queue."""

    generator: str
    settings: dict
    errors: list[str]


@dataclass(repr=False)
class Truth(ShortRepr):
    """Ground truth of a simulated bundle: video (C, T, H, W) float32 and its time grid."""

    video: np.ndarray
    frame_times_s: np.ndarray
    dt_s: float


@dataclass(repr=False)
class Bundle(ShortRepr):
    """A whole capture. `created_utc` is filled on write when empty; `rngcam_version` always."""

    rs: CameraRecord | None
    gs: CameraRecord | None
    calibration: Calibration = field(default_factory=Calibration)
    trigger: TriggerRecord | None = None
    truth: Truth | None = None
    rig_yaml: str = ""
    meta: dict = field(default_factory=dict)
    created_utc: str = ""
    rngcam_version: str = ""


# ----------------------------------------------------------------------------- validation


def is_warning(problem: str) -> bool:
    """True for a warning-level problem (the bundle is still usable)."""
    return problem.startswith(WARNING_PREFIX)


def camera_channels(record: CameraRecord) -> int:
    """Colour channels a camera delivers: C of (N, H, W, C) frames, 3 for Bayer mosaics, else 1."""
    shape = np.shape(record.frames)
    if len(shape) == 4:
        return int(shape[-1])
    return 3 if record.pixel_format.lower().startswith("bayer") else 1


def _finite(x: Any) -> bool:
    try:
        return x is not None and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def _check_camera(name: str, rec: CameraRecord) -> list[str]:
    label = name.upper()
    problems: list[str] = []
    shape = tuple(np.shape(rec.frames))
    dtype = np.dtype(rec.frames.dtype) if hasattr(rec.frames, "dtype") else None
    if len(shape) not in (3, 4):
        problems.append(f"{label} frames must be (N, H, W) or (N, H, W, C), got shape {shape}")
        n = shape[0] if shape else 0
    else:
        n = shape[0]
        if n < 1:
            problems.append(f"{label} has no frames")
    if dtype is None or dtype.kind not in "uif":
        problems.append(f"{label} frames must be integer or float, got dtype {dtype}")
    fmt = rec.pixel_format.lower() if isinstance(rec.pixel_format, str) else ""
    if not fmt:
        problems.append(f"{label} pixel_format is empty")
    elif fmt.startswith(("bayer", "mono")) and len(shape) != 3:
        problems.append(f"{label} pixel format {printable(rec.pixel_format, 40)} needs (N, H, W) frames, got {shape}")
    elif fmt.startswith(("rgb", "bgr")) and (len(shape) != 4 or shape[-1] != 3):
        problems.append(f"{label} pixel format {printable(rec.pixel_format, 40)} needs (N, H, W, 3) frames, "
                        f"got {shape}")
    if not isinstance(rec.bit_depth, (int, np.integer)) or rec.bit_depth < 1:
        problems.append(f"{label} bit_depth must be a positive integer, got {rec.bit_depth!r}")
    elif dtype is not None and dtype.kind in "ui" and rec.bit_depth > 8 * dtype.itemsize:
        problems.append(f"{label} bit_depth {rec.bit_depth} does not fit frames of dtype {dtype}")
    if not _finite(rec.black_level_dn) or rec.black_level_dn < 0:
        problems.append(f"{label} black_level_dn must be finite and >= 0, got {rec.black_level_dn!r}")
    if not _finite(rec.exposure_s) or rec.exposure_s <= 0:
        problems.append(f"{label} exposure_s must be finite and > 0, got {rec.exposure_s!r}")
    if not _finite(rec.gain_db):
        problems.append(f"{label} gain_db must be finite, got {rec.gain_db!r}")
    if rec.line_time_s is not None and (not _finite(rec.line_time_s) or rec.line_time_s <= 0):
        problems.append(f"{label} line_time_s must be finite and > 0, got {rec.line_time_s!r}")
    if rec.readout not in READOUTS:
        problems.append(f"{label} readout must be one of {', '.join(READOUTS)}, got "
                        f"{printable(repr(rec.readout), 60)}")
    trig = np.asarray(rec.trigger_times_s, dtype=np.float64)
    if trig.ndim != 1 or trig.shape[0] != n:
        problems.append(f"{label} trigger_times_s has shape {trig.shape}, expected ({n},) for {n} frames")
    if not np.all(np.isfinite(trig)):
        problems.append(f"{label} trigger_times_s has non-finite values")
    elif name == "rs" and trig.size and trig[0] != 0:
        problems.append(f"RS trigger_times_s is {trig[0]:.6g} s; times are relative to T0, the RS "
                        "trigger, so it must be 0 (subtract it from every trigger time)")
    for opt in ("timestamps_s", "frame_ids", "exposure_start_s"):
        arr = getattr(rec, opt)
        if arr is not None and np.shape(arr) != (n,):
            problems.append(f"{label} {opt} has shape {np.shape(arr)}, expected ({n},)")
    for opt in ("timestamps_s", "exposure_start_s"):
        arr = getattr(rec, opt)
        bad = arr is not None and (np.asarray(arr).dtype.kind not in "uif"
                                   or not np.all(np.isfinite(np.asarray(arr, float))))
        if bad:
            problems.append(f"{label} {opt} has non-finite values")
    if rec.frame_ids is not None and np.asarray(rec.frame_ids).dtype.kind not in "ui":
        problems.append(f"{label} frame_ids must be integers, got dtype {np.asarray(rec.frame_ids).dtype}")
    if not isinstance(rec.exposure_start_method, str):
        problems.append(f"{label} exposure_start_method must be text")
    if not isinstance(rec.features, dict):
        problems.append(f"{label} features must be a dict, got {type(rec.features).__name__}")
    return problems


def _check_gs_window(rs: CameraRecord, gs: CameraRecord) -> list[str]:
    """Warn about GS exposures not inside the RS exposure window [0, last row's end] (for top-down,
    (rows-1)*line_time + exposure; physics.timing.readout_lines for the other readout orders).

    A GS exposure before the window and one after it get the same treatment: a warning here,
    and the reconstruction leaves out a frame that does not overlap the window at all.
    """
    rs_trig = np.asarray(rs.trigger_times_s, dtype=np.float64)
    gs_trig = np.asarray(gs.trigger_times_s, dtype=np.float64)
    rs_shape = np.shape(rs.frames)
    if (rs_trig.size < 1 or len(rs_shape) < 3 or not _finite(rs.line_time_s) or rs.readout not in READOUTS
            or not _finite(rs.exposure_s) or not _finite(gs.exposure_s) or not np.all(np.isfinite(rs_trig))
            or gs_trig.ndim != 1 or not np.all(np.isfinite(gs_trig))):
        return []
    start = float(rs_trig[0])
    lines = readout_lines(rs.readout, rs_shape[2 if rs.readout == "columns" else 1]).max()
    end = start + lines * float(rs.line_time_s) + float(rs.exposure_s)
    gs_end = gs_trig + float(gs.exposure_s)
    tol = 1e-9 * max(abs(end), 1e-12)
    outside = np.flatnonzero((gs_trig < start - tol) | (gs_end > end + tol))
    if outside.size == 0:
        return []
    frames = ", ".join(f"{i + 1} [{gs_trig[i] * 1e3:.3f}, {gs_end[i] * 1e3:.3f}]" for i in outside[:5])
    message = (f"{WARNING_PREFIX}{outside.size} GS exposure(s) outside the RS exposure window "
               f"[{start * 1e3:.3f}, {end * 1e3:.3f}] ms after T0 (frame, ms): {frames}; "
               "a frame that misses the window entirely is left out of the reconstruction")
    return [message]


START_TOLERANCE = 0.1  # of a GS frame interval: a measured exposure start further from its plan is a warning


def gs_start_offsets(gs: CameraRecord | None) -> tuple[np.ndarray, float] | None:
    """(each GS frame's measured exposure start less its planned trigger time, the tolerance in
    seconds: a tenth of the planned frame interval, or of the exposure for one frame), or None
    when the bundle has no usable measured starts."""
    if gs is None or gs.exposure_start_s is None:
        return None
    measured = np.asarray(gs.exposure_start_s, np.float64)
    planned = np.asarray(gs.trigger_times_s, np.float64)
    if measured.shape != planned.shape or measured.ndim != 1 or not (np.all(np.isfinite(measured))
                                                                     and np.all(np.isfinite(planned))):
        return None
    interval = float(np.median(np.diff(planned))) if planned.size > 1 else float(gs.exposure_s)
    if not _finite(interval) or interval <= 0:
        interval = float(gs.exposure_s) if _finite(gs.exposure_s) else 0.0
    return measured - planned, START_TOLERANCE * interval


def _check_gs_starts(gs: CameraRecord) -> list[str]:
    """Warn when a GS exposure started more than a tenth of a frame interval from its plan."""
    found = gs_start_offsets(gs)
    if found is None:
        return []
    offsets, tol = found
    late = np.flatnonzero(np.abs(offsets) > tol)
    if late.size == 0:
        return []
    frames = ", ".join(f"{i + 1} {offsets[i] * 1e6:+.1f}" for i in late[:5])
    return [f"{WARNING_PREFIX}{late.size} GS frame(s) started more than a tenth of a frame interval "
            f"({tol * 1e6:.1f} us) away from the plan (frame, us): {frames}; the reconstruction uses "
            "the measured exposure starts"]


def _check_gs_size(rs: CameraRecord, gs: CameraRecord, cal: Calibration | None) -> list[str]:
    """GS frames of another size than the RS frames: a warning without a GS-to-RS homography to
    map them (recon refuses the GS frames then), or when that homography is the identity (the
    GS frame's edge would be repeated over the RS pixels it does not cover)."""
    rs_hw, gs_hw = tuple(np.shape(rs.frames))[1:3], tuple(np.shape(gs.frames))[1:3]
    if len(rs_hw) != 2 or len(gs_hw) != 2 or rs_hw == gs_hw:
        return []
    sizes = f"GS frames are {gs_hw[0]}x{gs_hw[1]} but RS frames are {rs_hw[0]}x{rs_hw[1]}"
    h = None if cal is None or cal.gs_to_rs is None else np.asarray(cal.gs_to_rs)
    if h is None or h.shape != (3, 3) or not np.all(np.isfinite(h)):
        return [f"{WARNING_PREFIX}{sizes}, and the bundle has no GS-to-RS alignment to map one onto "
                "the other: recon cannot use the GS frames (run `rngcam calibrate align`)"]
    if np.allclose(h, np.eye(3)):
        return [f"{WARNING_PREFIX}{sizes}, and the GS-to-RS alignment is the identity: "
                "is it the alignment of these cameras?"]
    return []


def _check_calibration(cal: Calibration, rs: CameraRecord | None) -> list[str]:
    problems: list[str] = []
    channels = camera_channels(rs) if rs is not None else None
    rs_shape = tuple(np.shape(rs.frames)) if rs is not None else ()
    if cal.psf is not None:
        psf = np.asarray(cal.psf)
        if psf.ndim != 3:
            problems.append(f"calibration psf must be (C, Hp, Wp), got shape {psf.shape}")
        elif not np.all(np.isfinite(psf)):
            problems.append("calibration psf has non-finite values")
        else:
            sums = psf.reshape(psf.shape[0], -1).sum(axis=1)
            if psf.size == 0 or np.any(sums <= 0) or psf.max() <= 0:
                problems.append("calibration psf has no positive signal in some channel")
            if channels is not None and psf.shape[0] not in (1, channels):
                problems.append(f"calibration psf has {psf.shape[0]} channels, RS delivers {channels}")
            if len(rs_shape) >= 3 and (psf.shape[1] > PSF_SIZE_RATIO * rs_shape[1]
                                       or psf.shape[2] > PSF_SIZE_RATIO * rs_shape[2]):
                problems.append(f"calibration psf {psf.shape} is more than {PSF_SIZE_RATIO}x the RS frame "
                                f"{rs_shape[1:3]} on a side: a PSF of another sensor or binning? "
                                "(crop it to the frame's size)")
    if cal.psf_bias is None or not _finite(cal.psf_bias):
        problems.append(f"calibration psf_bias must be finite, got {cal.psf_bias!r}")
    if cal.gs_to_rs is not None:
        h = np.asarray(cal.gs_to_rs)
        if h.shape != (3, 3):
            problems.append(f"calibration gs_to_rs must be 3x3, got shape {h.shape}")
        elif not np.all(np.isfinite(h)):
            problems.append("calibration gs_to_rs has non-finite values")
    if cal.white_balance is not None:
        wb = np.asarray(cal.white_balance)
        if wb.ndim != 1 or (channels is not None and wb.shape[0] != channels):
            problems.append(f"calibration white_balance has shape {wb.shape}, "
                            f"expected ({channels},) for the RS channels")
        elif not np.all(np.isfinite(wb)) or np.any(wb <= 0):
            problems.append("calibration white_balance must be finite and > 0")
    if cal.field_stop is not None:
        fs = np.asarray(cal.field_stop)
        if len(rs_shape) >= 3 and fs.shape != rs_shape[1:3]:
            problems.append(f"calibration field_stop has shape {fs.shape}, RS frames are {rs_shape[1:3]}")
        elif fs.ndim != 2:
            problems.append(f"calibration field_stop must be 2-D, got shape {fs.shape}")
        if fs.dtype != np.bool_:
            problems.append(f"calibration field_stop must be bool, got dtype {fs.dtype}")
        elif fs.size and not fs.any():
            problems.append("calibration field_stop blocks every pixel")
    if not isinstance(cal.extra, dict):
        problems.append(f"calibration extra must be a dict, got {type(cal.extra).__name__}")
    return problems


def _check_truth(truth: Truth) -> list[str]:
    problems: list[str] = []
    shape = tuple(np.shape(truth.video))
    times = np.asarray(truth.frame_times_s, dtype=np.float64)
    if len(shape) != 4:
        problems.append(f"truth video must be (C, T, H, W), got shape {shape}")
    elif times.ndim != 1 or times.shape[0] != shape[1]:
        problems.append(f"truth frame_times_s has shape {times.shape}, expected ({shape[1]},) "
                        f"for T={shape[1]} frames")
    if hasattr(truth.video, "dtype") and np.dtype(truth.video.dtype).kind != "f":
        problems.append(f"truth video must be float, got dtype {truth.video.dtype}")
    if not np.all(np.isfinite(times)):
        problems.append("truth frame_times_s has non-finite values")
    if not _finite(truth.dt_s) or truth.dt_s <= 0:
        problems.append(f"truth dt_s must be finite and > 0, got {truth.dt_s!r}")
    if isinstance(truth.video, np.ndarray) and truth.video.size and not np.all(np.isfinite(truth.video)):
        problems.append("truth video has non-finite values")
    return problems


def trigger_faults(errors: list) -> list[str]:
    """Entries of a SYST:ERR? read-back that are real errors (not '+0,"No error"')."""
    return [str(e) for e in errors if not str(e).lstrip("+ ").startswith("0,")]


def _check_trigger(trig: TriggerRecord) -> list[str]:
    problems: list[str] = []
    if not isinstance(trig.generator, str) or not trig.generator:
        problems.append("trigger generator identity is empty")
    if not isinstance(trig.settings, dict):
        problems.append(f"trigger settings must be a dict, got {type(trig.settings).__name__}")
    if not isinstance(trig.errors, list):
        problems.append(f"trigger errors must be a list, got {type(trig.errors).__name__}")
    else:
        real = trigger_faults(trig.errors)
        if real:
            problems.append(f"{WARNING_PREFIX}trigger generator reported {len(real)} error(s): "
                            + "; ".join(printable(e, 200) for e in real[:3]))
    return problems


def declared_cameras(meta) -> tuple[str, ...]:
    """The cameras a bundle says it has: ("rs",) where meta.cameras says RS only (an imported
    capture without GS frames), else both."""
    cams = meta.get("cameras") if isinstance(meta, dict) else None
    return ("rs",) if cams == ["rs"] else ("rs", "gs")


def check_bundle(bundle: Bundle, skip: frozenset[str] = frozenset()) -> list[str]:
    """Every problem of an in-memory bundle ([] when valid); warnings start with 'warning: '.

    Arrays may be numpy arrays or h5py datasets (only shapes are read from frames and video).
    `skip` names parts ("rs", "gs") already reported as broken, so they are not reported twice.
    """
    problems: list[str] = []
    cameras = declared_cameras(bundle.meta)
    for name in ("rs", "gs"):
        rec = getattr(bundle, name)
        if rec is None:
            if name not in skip and name in cameras:
                problems.append(f"missing {name.upper()} camera record (group '{name}')")
        else:
            problems += _check_camera(name, rec)
    if cameras == ("rs",) and bundle.gs is not None:
        problems.append("meta.cameras says the bundle is RS only, but it has a GS camera record")
    if bundle.rs is not None and bundle.rs.line_time_s is None:
        problems.append("RS camera has no line_time_s")
    if bundle.gs is not None and bundle.gs.line_time_s is not None:
        problems.append(f"{WARNING_PREFIX}GS camera has a line_time_s ({bundle.gs.line_time_s!r}); "
                        "a global shutter has none")
    if bundle.rs is not None and bundle.gs is not None:
        problems += _check_gs_window(bundle.rs, bundle.gs)
        problems += _check_gs_size(bundle.rs, bundle.gs, bundle.calibration)
    if bundle.gs is not None:
        problems += _check_gs_starts(bundle.gs)
    if bundle.calibration is not None:
        problems += _check_calibration(bundle.calibration, bundle.rs)
    if bundle.trigger is not None:
        problems += _check_trigger(bundle.trigger)
    if bundle.truth is not None:
        problems += _check_truth(bundle.truth)
    if not isinstance(bundle.meta, dict):
        problems.append(f"meta must be a dict, got {type(bundle.meta).__name__}")
    elif isinstance(bundle.meta.get("warnings"), list):  # what the capture warned about
        # text from the file: one printable line each, so a newline cannot forge a line of ours
        problems += [f"{WARNING_PREFIX}capture: {printable(w)}" for w in bundle.meta["warnings"]]
    if not isinstance(bundle.rig_yaml, str):
        problems.append(f"rig_yaml must be a string, got {type(bundle.rig_yaml).__name__}")
    return problems
