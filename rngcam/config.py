"""Rig files: pydantic models, loading with clear errors, and path resolution.

A rig file (YAML, SI units, names carry the unit) describes the two cameras, the trigger
timing, the function generator, the calibration inputs and, for the mock rig, the scene.
`load_rig(path)` returns a `Rig` (the validated model, the file path and its text verbatim)
or raises ConfigError with one line naming the file, the field and the problem.
"""

from __future__ import annotations

import difflib
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rngcam.backends import CAMERAS, GENERATORS, camera_backend, generator_transport
from rngcam.errors import ConfigError
from rngcam.paths import PACKAGE_PREFIX
from rngcam.physics.timing import DEFAULT_READOUT, check_readout
from rngcam.untrusted import MAX_YAML_CHARS, check_yaml_shape, printable, read_untrusted

Dialect = Literal["keysight_33500b", "rigol_dg", "siglent_sdg"]
FakeFault = Literal["none", "silent", "garbage", "scpi_error"]

# Relative tolerance for "equally spaced" GS triggers (a burst has one period).
_SPACING_RTOL = 1e-6


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Roi(_Model):
    """Sensor region of interest in pixels (offsets from the top-left corner)."""

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    offset_x: int = Field(default=0, ge=0)
    offset_y: int = Field(default=0, ge=0)


class TriggerInput(_Model):
    """How a camera is triggered: its input line, edge, and the generator channel wired to it."""

    source: str = "Line1"
    activation: Literal["RisingEdge", "FallingEdge"] = "RisingEdge"
    channel: int = Field(ge=1, le=4)
    debouncer_s: float | None = Field(default=None, ge=0)


class MockMisalignment(_Model):
    """A mock GS camera's true GS-to-RS similarity about the image centre: GS pixel p sees the
    scene point (RS pixel) scale * R(rotation) (p - centre) + centre + shift."""

    shift_px: tuple[float, float] = (0.0, 0.0)
    rotation_deg: float = 0.0
    scale: float = Field(default=1.0, gt=0)


class MockSensor(_Model):
    """Physics of a mock camera (it renders frames from the rig's mock scene).

    line_time_s: the mock RS camera's true line time (defaults to the rig's line_time_s, set it
    differently to exercise the capture's timing warning). readout_s: the time after an
    exposure during which a GS mock ignores further triggers (like a real sensor's readout).
    """

    noise: bool = True
    seed: int = 0
    bit_depth: int = Field(default=12, ge=8, le=16)
    black_level_dn: float = Field(default=64.0, ge=0)
    full_well_e: float = Field(default=10_000.0, gt=0)
    read_noise_e: float = Field(default=3.0, ge=0)
    line_time_s: float | None = Field(default=None, gt=0)
    readout_s: float = Field(default=1e-3, ge=0)
    channel_gain: list[float] | None = None  # per-channel sensitivity (calibration tests: GS/RS gains)
    misalignment: MockMisalignment | None = None  # GS only: how it sees the scene (calibrate align)


class CameraConfig(_Model):
    """One camera. `serial` identifies it (cameras are never opened by list index)."""

    backend: str  # a name in rngcam.backends.CAMERAS
    serial: str = Field(min_length=1)
    model: str = ""
    cti: str | None = None  # genicam: GenTL producer file; else $RNGCAM_CTI
    pylon_transport: str | None = None  # pylon: restrict to one transport layer, e.g. BaslerCamEmu
    address: str | None = None  # aravis: the camera's IP address (opened directly, no discovery)
    readout_s: float | None = Field(default=None, gt=0)  # sensor readout at this ROI, when the camera cannot say
    pixel_format: str
    exposure_s: float = Field(gt=0, le=10.0)
    gain_db: float = Field(default=0.0, ge=0)
    roi: Roi
    line_time_s: float | None = Field(default=None, gt=0, le=1e-2)  # RS: the expected line time
    readout: str = DEFAULT_READOUT  # RS: the sensor's readout order, one of physics.timing.READOUTS
    black_level_dn: float = Field(default=0.0, ge=0)
    trigger: TriggerInput
    fetch_timeout_s: float = Field(default=2.0, gt=0)
    chunk_timestamps: bool = True
    mock: MockSensor | None = None

    @field_validator("backend")
    @classmethod
    def _known_backend(cls, v: str) -> str:
        camera_backend(v)  # ValueError naming the known ones
        return v

    @field_validator("readout", mode="before")
    @classmethod
    def _known_readout(cls, v):
        return check_readout(v)  # ValueError naming the readout orders

    @property
    def bit_depth(self) -> int:
        """Bit depth implied by the pixel format (Mono12, BayerRG12, RGB12 ... -> 12)."""
        digits = "".join(ch for ch in self.pixel_format if ch.isdigit())
        return int(digits) if digits else 8


class Cameras(_Model):
    rs: CameraConfig
    gs: CameraConfig


class TimingConfig(_Model):
    """Trigger times relative to the moment the generator fires (the RS trigger is T0)."""

    rs_trigger_s: float = Field(default=0.0, ge=0)
    gs_trigger_s: list[float] = Field(min_length=1)
    pulse_width_s: float = Field(default=100e-6, gt=0)

    @field_validator("gs_trigger_s")
    @classmethod
    def _increasing_equally_spaced(cls, v: list[float]) -> list[float]:
        if any(not math.isfinite(t) or t < 0 for t in v):
            raise ValueError("GS trigger times must be finite and >= 0")
        steps = [b - a for a, b in itertools.pairwise(v)]
        if any(s <= 0 for s in steps):
            raise ValueError("GS trigger times must be strictly increasing")
        if steps and max(steps) - min(steps) > _SPACING_RTOL * max(steps):
            raise ValueError("GS trigger times must be equally spaced (the generator sends them "
                             f"as one burst with one period); steps are {steps}")
        return v

    @property
    def gs_period_s(self) -> float | None:
        g = self.gs_trigger_s
        return (g[-1] - g[0]) / (len(g) - 1) if len(g) > 1 else None

    @model_validator(mode="after")
    def _pulse_fits(self) -> TimingConfig:
        problems = []
        period = self.gs_period_s
        if period is not None and self.pulse_width_s >= period:
            problems.append(f"pulse_width_s ({self.pulse_width_s}) must be shorter than the GS "
                            f"trigger period ({period})")
        if self.rs_trigger_s > self.gs_trigger_s[0] + 1e-12:
            problems.append("the RS trigger (T0) must not come after the first GS trigger")
        return _raise_all(problems, self)


class GeneratorConfig(_Model):
    """The function generator: SCPI dialect and transport ('fake' spawns a simulated one).

    visa_library: the pyvisa backend ("@py" for pyvisa-py, "sim" for rngcam's pyvisa-sim
    definitions of the three instruments, default: the system VISA). link: "trigger_out" when the
    RS channel's trigger output is cabled into the GS channel's trigger input (Rigol), so one
    manual trigger fires both trains."""

    dialect: Dialect
    transport: str = "serial"  # a name in rngcam.backends.GENERATORS
    port: str | None = None
    visa_resource: str | None = None
    visa_library: str | None = None
    link: Literal["none", "trigger_out"] = "none"
    baudrate: int = Field(default=9600, gt=0)
    timeout_s: float = Field(default=1.0, gt=0)
    high_v: float = 5.0
    low_v: float = 0.0
    fake_fault: FakeFault = "none"  # test hook for the fake instrument only

    @field_validator("transport")
    @classmethod
    def _known_transport(cls, v: str) -> str:
        generator_transport(v)  # ValueError naming the known ones
        return v

    @model_validator(mode="after")
    def _transport_fields(self) -> GeneratorConfig:
        problems = []
        if self.link == "trigger_out" and self.dialect != "rigol_dg":
            problems.append(f"link 'trigger_out' is wired for rigol_dg only ({self.dialect} fires both channels "
                            "itself or has no per-channel trigger output)")
        if self.transport == "serial" and not self.port:
            problems.append("transport 'serial' needs 'port' (e.g. /dev/ttyUSB0 or COM3)")
        if self.transport == "visa" and not self.visa_resource:
            problems.append("transport 'visa' needs 'visa_resource' (e.g. USB0::...::INSTR)")
        if self.transport == "fake" and self.port:
            problems.append("transport 'fake' opens its own pseudo-terminal; remove 'port'")
        if self.fake_fault != "none" and self.transport != "fake":
            problems.append("fake_fault only applies to transport 'fake'")
        if not self.high_v > self.low_v:
            problems.append(f"high_v ({self.high_v}) must exceed low_v ({self.low_v})")
        return _raise_all(problems, self)


class PsfConfig(_Model):
    """PSF file (relative paths are relative to the rig file), crop fraction and dark level."""

    path: str
    crop: float = Field(default=1.0, gt=0, le=1)
    bias: float | Literal["auto"] = "auto"


class CalibrationConfig(_Model):
    psf: PsfConfig | None = None
    file: str | None = None  # rngcam calibrate's HDF5 (relative to the rig); overrides the values below
    gs_to_rs: list[list[float]] | None = None  # 3x3 homography, GS pixel -> RS pixel
    white_balance: list[float] | None = None

    @field_validator("gs_to_rs")
    @classmethod
    def _three_by_three(cls, v):
        if v is not None and (len(v) != 3 or any(len(r) != 3 for r in v)):
            raise ValueError("gs_to_rs must be a 3x3 matrix (a list of three rows of three)")
        return v


class ReconConfig(_Model):
    """How the reconstruction bins the RS sensor (grid_bin x grid_bin sensor pixels per grid
    pixel), so one video frame lasts line time x grid_bin. Written to the bundle's meta."""

    grid_bin: int = Field(default=1, ge=1)


class MockSceneConfig(_Model):
    """The scene mock cameras look at (rngcam.sim.scenes), rendered on the reconstruction grid
    (the RS sensor size / recon.grid_bin) and repeated to sensor-size frames, and how the mock
    RS sensor's timing differs from what the rig says, as a real one's does:

    true_line_time_s: the sensor's actual line time (default: cameras.rs.mock.line_time_s, else
    the rig's cameras.rs.line_time_s). readout_time_bias: the mock's SensorReadoutTime grows by
    (1 + bias) x the true line time per row (plus a constant), a rough figure as the vendor warns.
    led_level: the brightness (fraction of full scale) of the LED a generator channel drives
    steady at 5 V through the diffuser (rngcam calibrate linetime --flicker).
    Clocks and exposure starts (rngcam.acquire.mock_clock): each mock camera's timestamp counter
    (1 ns ticks) runs at (1 + drift) x host time + offset, the RS camera's at clock_offset_s and
    clock_drift_ppm, the GS camera's at their negatives; timestamp_latch: whether the cameras
    have a timestamp latch (else capture fits ticks against host times). gs_start_offset_s: every
    GS exposure starts this long after its trigger (a debouncer and model delay), plus a
    per-frame gaussian jitter of start_jitter_s (seeded, clipped at 4 sigmas; the mock refuses an
    exposure before T0, so with a GS trigger at T0 keep the offset >= 4 x the jitter)."""

    scene: str = "sineball"
    seed: int = 0
    options: dict[str, Any] = Field(default_factory=dict)
    true_line_time_s: float | None = Field(default=None, gt=0, le=1e-2)
    readout_time_bias: float = Field(default=0.015, gt=-0.5, lt=0.5)
    led_level: float = Field(default=0.5, ge=0, le=100)
    clock_offset_s: float = Field(default=12.5, ge=-1e6, le=1e6)
    clock_drift_ppm: float = Field(default=20.0, ge=-1000, le=1000)
    timestamp_latch: bool = True
    gs_start_offset_s: float = Field(default=0.0, ge=-1.0, le=1.0)
    start_jitter_s: float = Field(default=0.0, ge=0.0, le=1.0)


class RigConfig(_Model):
    name: str
    description: str = ""
    cameras: Cameras
    timing: TimingConfig
    generator: GeneratorConfig
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    recon: ReconConfig = Field(default_factory=ReconConfig)
    mock: MockSceneConfig | None = None

    @model_validator(mode="after")
    def _consistent(self) -> RigConfig:
        rs, gs = self.cameras.rs, self.cameras.gs
        problems = []
        if rs.line_time_s is None:
            problems.append("cameras.rs.line_time_s is required (the RS row-to-row delay)")
        period = self.timing.gs_period_s
        if period is not None and period < gs.exposure_s + (gs.readout_s or 0.0):
            problems.append(f"timing.gs_trigger_s: GS triggers {period * 1e3:.4g} ms apart, but each GS frame needs "
                            f"at least its exposure ({gs.exposure_s * 1e3:.4g} ms"
                            + (f") + readout_s ({gs.readout_s * 1e3:.4g} ms)" if gs.readout_s else ")")
                            + ": the camera would miss triggers")
        if rs.trigger.channel == gs.trigger.channel:
            problems.append("cameras.rs.trigger.channel and cameras.gs.trigger.channel must "
                            "differ (one pulse for the RS camera, a burst for the GS camera)")
        simulated = [CAMERAS[c.backend].simulated for c in (rs, gs)]
        fake_generator = GENERATORS[self.generator.transport].simulated
        if any(simulated):
            if not all(simulated) or rs.backend != gs.backend:
                problems.append(f"simulated cameras ({', '.join(n for n, s in CAMERAS.items() if s.simulated)}) "
                                "cannot be mixed with other backends in one rig")
            if not fake_generator:
                problems.append("simulated cameras only receive triggers from generator transport 'fake'")
        elif fake_generator:
            problems.append("generator transport 'fake' can only trigger simulated cameras")
        if rs.backend == "mock" or gs.backend == "mock":
            if self.mock is None:
                problems.append("mock cameras need a 'mock' section naming the scene")
            if rs.roi != gs.roi:
                problems.append("mock cameras need equal ROIs (the scene is rendered once and seen by both)")
            b = self.recon.grid_bin
            if rs.roi.width % b or rs.roi.height % b:
                problems.append(f"mock cameras: the ROI {rs.roi.width}x{rs.roi.height} must divide by "
                                f"recon.grid_bin {b} (the mock renders on the grid and repeats each pixel)")
        return _raise_all(problems, self)


@dataclass(frozen=True)
class Rig:
    """A loaded rig: the validated model, where it came from, and its text verbatim."""

    config: RigConfig
    path: Path
    text: str

    def resolve(self, relative: str | Path) -> Path:
        """A path from the rig file, relative to the rig file's folder."""
        p = Path(relative).expanduser()
        return p if p.is_absolute() else (self.path.parent / p).resolve()

    def leaves_folder(self, path: str | Path) -> bool:
        """True when `path` (links followed) lies outside the rig file's folder."""
        return not Path(path).resolve().is_relative_to(self.path.parent.resolve())

    def paths_outside(self) -> list[tuple[str, Path]]:
        """(rig field, path) of each file the rig names to read that lies outside its folder
        (`package:` names stay inside rngcam/data: rngcam.paths)."""
        cal = self.config.calibration
        named = [("calibration.file", cal.file)]
        if cal.psf is not None and not cal.psf.path.startswith(PACKAGE_PREFIX):
            named.append(("calibration.psf.path", cal.psf.path))
        return [(key, self.resolve(p)) for key, p in named if p and self.leaves_folder(self.resolve(p))]

    def outside_warnings(self) -> list[str]:
        """One warning line for each file the rig reads from outside its folder (`paths_outside`)."""
        return [f"warning: {printable(self.path)}: {key} reads {printable(p)}, outside the rig's folder "
                f"{printable(self.path.parent)} (check a rig from elsewhere before using it)"
                for key, p in self.paths_outside()]


def _raise_all(problems: list[str], model):
    """A model validator's end: every problem it found in one ValueError, or the model."""
    if problems:
        raise ValueError("; ".join(problems))
    return model


def _location(loc: tuple) -> str:
    return ".".join(str(part) for part in loc) or "(top level)"


def format_validation_error(path: Path, exc: ValidationError) -> str:
    """One line naming every problem: 'FILE: field.path: problem; other.field: problem ...'.

    Unknown fields come first, with the missing name they most resemble as a suggestion; a
    missing field that is the suggestion for a misspelt one is not listed again.
    """
    errors = sorted(exc.errors(), key=lambda e: e["type"] != "extra_forbidden")
    suggested: set[tuple] = set()
    parts = []
    for e in errors:
        loc = tuple(e["loc"])
        if e["type"] == "missing" and loc in suggested:
            continue
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            missing = [str(m["loc"][-1]) for m in errors
                       if m["type"] == "missing" and m["loc"][:-1] == e["loc"][:-1]]
            close = difflib.get_close_matches(str(loc[-1]), missing, n=1)
            if close:
                suggested.add((*loc[:-1], close[0]))
            msg = "unknown field" + (f" (did you mean {close[0]!r}?)" if close else " (check the spelling)")
        parts.append(f"{_location(loc)}: {msg}")
    return f"{path}: " + "; ".join(parts)


def parse_rig(text: str, path: str | Path = "<rig>") -> Rig:
    """Validate rig YAML text; `path` names it in errors and anchors relative paths."""
    path = Path(path)
    try:
        check_yaml_shape(text, str(path), error=ConfigError)  # size and nesting first: nothing built yet
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}: {where}not valid YAML ({problem})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a rig file must be a YAML mapping, got {type(data).__name__}")
    try:
        config = RigConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(path, exc)) from None
    return Rig(config=config, path=path.resolve() if path.name != "<rig>" else path, text=text)


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig file; ConfigError (one line) when it is missing or invalid."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        raise ConfigError(f"{path}: rig file not found")
    data = read_untrusted(path, MAX_YAML_CHARS * 4, what="rig file", error=ConfigError)  # no link, FIFO, device
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: cannot read rig file ({exc})") from None
    return parse_rig(text, path)
