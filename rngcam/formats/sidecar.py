"""The import sidecar: a YAML file that says what a capture's pixels cannot (rngcam import).

SI units, names carry the unit, as in rig files. `load_sidecar(path)` returns the validated
`Sidecar` or raises SidecarError with one line naming every missing or inconsistent field and
what to put there; `TEMPLATE` is the commented file `rngcam import --template` writes.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rngcam.errors import RngcamError
from rngcam.physics.timing import DEFAULT_READOUT, READOUTS
from rngcam.untrusted import printable, read_untrusted

MAX_SIDECAR_BYTES = 4 * 2**20  # a sidecar is a few hundred lines; a larger file is not one
MAX_TIMES = 100_000  # GS frame times in one sidecar
MAX_NODES = 1_000_000  # values in a sidecar, aliases expanded
PIXEL_FAMILIES = ("mono", "rgb", "BayerRG", "BayerGR", "BayerGB", "BayerBG")
LINE_TIME_SOURCES = ("flicker", "datasheet", "register", "simulated", "other")

# What to put where a field is missing: the second half of its line.
HINTS = {
    "rs": "the RS camera's section (rs: with line_time_s, exposure_s, bit_depth)",
    "psf": "the PSF's section (psf: with its file, or pass --psf)",
    "rs.line_time_s": ("the RS row-to-row delay in seconds, e.g. 13e-6 (measure it with `rngcam calibrate "
                       "linetime`, or take it from the datasheet or the camera's register)"),
    "rs.line_time_source": f"where the line time came from: one of {', '.join(LINE_TIME_SOURCES)}",
    "rs.exposure_s": "the RS exposure time in seconds, e.g. 650e-6",
    "rs.bit_depth": "the bits per pixel the RS camera delivered (8, 10, 12, 14 or 16)",
    "gs.exposure_s": "the GS exposure time in seconds",
    "gs.bit_depth": "the bits per pixel the GS camera delivered (8, 10, 12, 14 or 16)",
    "truth.dt_s": "the truth video's frame interval in seconds",
}


class SidecarError(RngcamError):
    """A sidecar (or the files it names) is missing, malformed or inconsistent."""


def plain_name(v: str | None) -> str | None:
    """`v` when it is a plain file name (no folder part), for files named in the sidecar."""
    if v is not None and (v in ("", ".", "..") or "/" in v or "\\" in v or "\x00" in v):
        raise ValueError("must be a plain file name in the sidecar's folder (no folders); "
                         "name files elsewhere on the command line (--rs, --gs, --psf)")
    return v


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ImageFile(_Model):
    """Where an array is: a file (a plain name in the sidecar's folder; the command line's option
    wins), the variable inside an NPZ or MATLAB file, and its axes when they cannot be inferred."""

    file: str | None = None
    variable: str | None = Field(default=None, max_length=200)
    axes: str | None = Field(default=None, pattern=r"^[NTHWYXCS]{2,4}$")

    @field_validator("file")
    @classmethod
    def _plain(cls, v):
        return plain_name(v)


class Camera(ImageFile):
    """What both cameras share."""

    pixel_format: str = Field(default="mono", max_length=40)
    bit_depth: int = Field(ge=1, le=16)
    black_level_dn: float = Field(default=0.0, ge=0)
    exposure_s: float = Field(gt=0, le=3600)
    gain_db: float = 0.0
    binning: int = Field(default=1, ge=1, le=64)
    pixel_pitch_um: float | None = Field(default=None, gt=0)
    model: str = Field(default="", max_length=200)
    serial: str = Field(default="", max_length=200)
    features: dict = Field(default_factory=dict)  # anything else the camera reported, kept as given
    # Each frame's exposure start as the camera's clock measured it, s on the RS trigger's timeline
    # (bundle rs|gs/exposure_start_s), and how it was measured; the reconstruction uses them.
    measured_starts_s: list[float] | None = Field(default=None, max_length=MAX_TIMES)
    measured_starts_method: str = Field(default="", max_length=200)

    @field_validator("pixel_format")
    @classmethod
    def _format(cls, v):
        family = pixel_family(v)
        if family is None:
            raise ValueError(f"must be one of {', '.join(PIXEL_FAMILIES)} (or a full name such as "
                             "RGB12, Mono12, BayerRG12)")
        return v

    @model_validator(mode="after")
    def _black_below_full_scale(self):
        if self.black_level_dn >= 2 ** self.bit_depth - 1:
            raise ValueError(f"black_level_dn {self.black_level_dn:g} is at or above the full scale of "
                             f"{self.bit_depth} bits ({2 ** self.bit_depth - 1})")
        return self


class RSCamera(Camera):
    """The rolling-shutter camera: its line time (and where it came from) and readout."""

    line_time_s: float = Field(gt=0, le=1)
    line_time_source: Literal["flicker", "datasheet", "register", "simulated", "other"]
    readout: str = DEFAULT_READOUT
    first_row_offset_s: float = Field(default=0.0, ge=0, le=3600)

    @field_validator("readout")
    @classmethod
    def _readout(cls, v):
        if v not in READOUTS:
            raise ValueError(f"must be one of {', '.join(READOUTS)}")
        return v


class GSCamera(Camera):
    """The global-shutter camera: when each frame's exposure started, on the RS trigger's clock
    (frame_times_s), or its trigger times and the delay from trigger to exposure."""

    frame_times_s: list[float] | None = Field(default=None, max_length=MAX_TIMES)
    trigger_times_s: list[float] | None = Field(default=None, max_length=MAX_TIMES)
    trigger_delay_s: float = Field(default=0.0, ge=0, le=3600)

    @model_validator(mode="after")
    def _times(self):
        given = [n for n in ("frame_times_s", "trigger_times_s") if getattr(self, n) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of frame_times_s (each exposure's start, seconds after the "
                             "RS trigger) or trigger_times_s (with trigger_delay_s)")
        times = getattr(self, given[0])
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError(f"{given[0]} must increase from frame to frame")
        return self

    def exposure_starts_s(self) -> list[float]:
        """Each frame's exposure start on the RS trigger's clock (before the first-row offset)."""
        if self.frame_times_s is not None:
            return list(self.frame_times_s)
        return [t + self.trigger_delay_s for t in self.trigger_times_s]


class PSF(ImageFile):
    """The point-spread function on the RS sensor: the level to subtract (a number or auto), any
    bias already subtracted from the file's values, and the sensor binning it was recorded at."""

    bias: float | Literal["auto"] = 0.0
    subtracted_bias: float = 0.0
    binning: int = Field(default=1, ge=1, le=64)
    source: str = Field(default="", max_length=500)


class CalibrationPart(_Model):
    """What is known of how the cameras map onto each other and their colours, and the field
    stop (an image the RS frame's size, nonzero where light reaches the sensor)."""

    gs_to_rs: list[list[float]] | None = None
    field_stop_file: str | None = None
    white_balance: list[float] | None = Field(default=None, max_length=4)
    source: str = Field(default="", max_length=500)
    extra: dict = Field(default_factory=dict)

    @field_validator("field_stop_file")
    @classmethod
    def _plain(cls, v):
        return plain_name(v)

    @field_validator("gs_to_rs")
    @classmethod
    def _three_by_three(cls, v):
        if v is not None and (len(v) != 3 or any(len(row) != 3 for row in v)):
            raise ValueError("must be a 3x3 matrix (three rows of three numbers): GS pixel (x, y, 1) -> RS pixel")
        return v

    @field_validator("white_balance")
    @classmethod
    def _gains(cls, v):
        if v is not None and any(g <= 0 for g in v):
            raise ValueError("every gain must be > 0")
        return v


class TruthPart(ImageFile):
    """A simulated capture's true video (C, T, H, W), frames dt_s apart from start_s."""

    dt_s: float = Field(gt=0)
    start_s: float = 0.0


class Sidecar(_Model):
    """The whole sidecar."""

    description: str = Field(default="", max_length=2000)
    rs: RSCamera
    gs: GSCamera | None = None
    psf: PSF
    calibration: CalibrationPart = CalibrationPart()
    truth: TruthPart | None = None
    meta: dict = Field(default_factory=dict)  # kept in the bundle's meta as given
    rig_yaml: str = Field(default="", max_length=200_000)  # a rig file's text, kept verbatim (never run)


def pixel_family(name: str) -> str | None:
    """The family of a pixel format (mono, rgb, BayerRG ...), by family or full name; None if unknown."""
    if not isinstance(name, str):
        return None
    stem = name.rstrip("0123456789")
    for family in PIXEL_FAMILIES:
        if stem.lower() == family.lower():
            return family
    return None


def _hint(loc: tuple) -> str:
    key = ".".join(str(p) for p in loc)
    return HINTS.get(key, "")


def describe(path: Path | str, exc: ValidationError) -> str:
    """One line: every field pydantic refused, each named with what to put there."""
    parts = []
    for e in exc.errors():
        loc = tuple(e["loc"])
        name = ".".join(str(p) for p in loc) or "the sidecar"
        if e["type"] == "missing":
            hint = _hint(loc)
            parts.append(f"{name}: missing" + (f"; put {hint}" if hint else ""))
        elif e["type"] == "extra_forbidden":
            parts.append(f"{name}: unknown field (see `rngcam import --template`)")
        else:
            parts.append(f"{name}: {e['msg'].removeprefix('Value error, ')}")
    return f"sidecar {path}: " + "; ".join(parts)


def _too_many_nodes(data, limit: int) -> bool:
    """Whether `data` holds more than `limit` values counted as written out: YAML aliases repeat a
    value without its text, so a small file can stand for a huge one (stored as JSON later)."""
    stack, count = [data], 0
    while stack:
        item = stack.pop()
        count += 1
        if count > limit:
            return True
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, (list, tuple, set)):
            stack.extend(item)
    return False


def parse_sidecar(text: str, path: Path | str = "<sidecar>") -> Sidecar:
    """Validate sidecar YAML text (safe loading: nothing in it runs); SidecarError, one line."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SidecarError(f"sidecar {path}: {where}not valid YAML ({printable(problem, 200)})") from None
    except RecursionError:
        raise SidecarError(f"sidecar {path}: nested too deeply to be a sidecar") from None
    if _too_many_nodes(data, MAX_NODES):
        raise SidecarError(f"sidecar {path}: more than {MAX_NODES:,} values once its aliases are expanded; "
                           "a sidecar is a few hundred")
    if not isinstance(data, dict):
        raise SidecarError(f"sidecar {path}: must be a YAML mapping (rs:, psf:, ...), got {type(data).__name__}; "
                           "start from `rngcam import --template`")
    try:
        return Sidecar.model_validate(data)
    except ValidationError as exc:
        raise SidecarError(printable(describe(path, exc), 4000)) from None


def load_sidecar(path: Path | str, digests: dict | None = None) -> Sidecar:
    """Read and validate a sidecar file (a regular file of at most MAX_SIDECAR_BYTES); `digests`
    gets the sha256 of what was read, by path."""
    path = Path(path)
    data = read_untrusted(path, MAX_SIDECAR_BYTES, what="sidecar", error=SidecarError)
    if digests is not None:
        digests[str(path)] = hashlib.sha256(data).hexdigest()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise SidecarError(f"sidecar {path}: not UTF-8 text") from None
    return parse_sidecar(text, path)


def finite(values) -> bool:
    """Whether every number in `values` (nested lists) is finite."""
    if isinstance(values, (list, tuple)):
        return all(finite(v) for v in values)
    return isinstance(values, (int, float)) and math.isfinite(values)


TEMPLATE = """\
# rngcam import sidecar: what the pixels cannot say. SI units; every name carries its unit.
# Fill in the fields marked REQUIRED, then: rngcam import THIS.yaml -o capture.h5
# Files are plain names in this file's folder, or given on the command line (--rs, --gs, --psf).
description: ""

rs:                            # the rolling-shutter camera
  file: rs.tif                 # TIFF, PNG, NPY/NPZ or MATLAB .mat (v5 or v7.3)
  variable: null               # the array's name inside an NPZ or .mat holding several
  axes: null                   # e.g. HW, HWC, CHW (default: inferred; MATLAB stacks are HWN)
  pixel_format: mono           # mono, rgb, BayerRG, BayerGR, BayerGB or BayerBG
  bit_depth: null              # REQUIRED: bits per pixel delivered (8, 10, 12, 14, 16)
  black_level_dn: 0            # the sensor's offset in DN, subtracted before use
  exposure_s: null             # REQUIRED: exposure time, e.g. 650.0e-6
  line_time_s: null            # REQUIRED: row-to-row delay, e.g. 13.0e-6
  line_time_source: null       # REQUIRED: flicker (rngcam calibrate linetime), datasheet, register, simulated, other
  readout: top-down            # top-down, bottom-up, columns, centre-out, edges-in, global-reset
  first_row_offset_s: 0.0      # first row's exposure start after the RS trigger
  gain_db: 0.0
  binning: 1                   # sensor binning the image was recorded at
  pixel_pitch_um: null         # sensor pixel pitch (after binning), for the record
  measured_starts_s: null      # the exposure start the camera's clock measured, if known
  model: ""
  serial: ""

gs:                            # the global-shutter camera; delete this section for an RS-only capture
  file: gs.tif                 # a TIFF stack, an image folder (--gs DIR) or a video file (--gs clip.mp4)
  pixel_format: mono           # its own format, bit depth and size: nothing is assumed equal to the RS
  bit_depth: null              # REQUIRED
  black_level_dn: 0
  exposure_s: null             # REQUIRED
  frame_times_s: null          # REQUIRED (or trigger_times_s): each exposure's start, s after the RS trigger
  # trigger_times_s: [0.0, 1.0e-3]   # instead of frame_times_s: the triggers ...
  # trigger_delay_s: 0.0             # ... and the delay from trigger to exposure start
  gain_db: 0.0
  binning: 1
  pixel_pitch_um: null

psf:                           # the point-spread function on the RS sensor's pixels
  file: psf.tif
  variable: null
  bias: 0.0                    # the background level in the file to subtract (a number, or auto)
  subtracted_bias: 0.0         # a bias already taken off the file's values, for the record
  binning: 1                   # sensor binning the PSF was recorded at (binned to the image's)
  source: ""                   # how it was measured

calibration:
  gs_to_rs: null               # 3x3 homography GS pixel (x, y, 1) -> RS pixel; REQUIRED when the sizes differ
  white_balance: null          # per-channel GS/RS gains, e.g. [1.0, 1.0, 1.0]
  field_stop_file: null        # an image the RS frame's size, nonzero where light reaches the sensor
  source: ""                   # where these came from (rngcam calibrate align, ...)
"""
