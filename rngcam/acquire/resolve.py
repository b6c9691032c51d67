"""The rig and its calibration merged once, before anything is captured.

`resolve_rig` reads the three places a value can come from and decides once which one holds:

- the rig file (`cameras.rs.line_time_s`, `calibration.psf`, `calibration.gs_to_rs`,
  `calibration.white_balance`, each camera's `black_level_dn`);
- the calibration file the rig names (`calibration.file`, written by `rngcam calibrate`): its
  line time, PSF, transform and white balance replace the rig's;
- the mock section of a mock camera (`cameras.*.mock`): the black level a mock sensor really
  has, and the hidden truths a calibration of the mock rig should recover (`MockTruth`: its
  true line time, transform and gains; they never go into a bundle as measured values).

Capture, calibration and the mock cameras all read the result, and the bundle records which
source each value came from (`sources`, shown by `rngcam inspect`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rngcam.acquire import libraries
from rngcam.config import CameraConfig, MockSceneConfig, MockSensor, Rig
from rngcam.errors import ConfigError
from rngcam.formats.bundle import Calibration
from rngcam.formats.calibration import StoredCalibration, rig_calibration
from rngcam.paths import resolve_data_ref
from rngcam.physics.geometry import similarity_matrix
from rngcam.physics.psf import load_psf, normalise, prepare_psf, resample, spectral_support, subtract_bias
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid

Progress = Callable[[str], None]
ROLES = ("rs", "gs")
SOURCE_ORDER = ("line_time_s", "psf", "gs_to_rs", "white_balance", "rs_black_level_dn", "gs_black_level_dn")
SOURCE_NAMES = {"rig": "the rig file", "calibration": "the calibration file", "mock": "the mock sensor",
                "default": "the default"}


@dataclass(frozen=True)
class MockTruth:
    """What a mock rig really is, hidden from the bundle: calibration on it reports its error
    against these. `line_time_s` is the mock RS sensor's, `gs_to_rs` (3x3) how the mock GS
    camera sees the scene, `white_balance` (C,) the RS/GS channel gain ratio; `readout_bias` how
    rough the mock's SensorReadoutTime is, `led_level` how bright a generator-driven LED looks
    (the rig's mock section)."""

    line_time_s: float
    gs_to_rs: np.ndarray
    white_balance: np.ndarray
    sensors: dict[str, MockSensor]
    readout_bias: float = 0.0
    led_level: float = 0.0


@dataclass
class ResolvedRig:
    """Every value capture records and calibration starts from, each with its source."""

    rig: Rig
    line_time_s: float
    gs_to_rs: np.ndarray
    white_balance: np.ndarray
    black_level_dn: dict[str, float]
    sources: dict[str, str]
    psf: np.ndarray | None = None  # (C, H, W) on the RS sensor grid, sum 1 per channel
    psf_source: str = ""
    psf_bias: float = 0.0
    rig_psf: np.ndarray | None = None  # the rig file's PSF: the mock cameras' optics
    calibration_file: Path | None = None
    stored: StoredCalibration | None = None
    mock: MockTruth | None = None
    extra: dict = field(default_factory=dict)

    def timing(self) -> tuple[RollingShutterTiming, GlobalShutterTiming, VideoGrid]:
        """RS/GS timing relative to T0 with the resolved line time, and the video grid."""
        c = self.rig.config
        cam = c.cameras.rs
        rs = RollingShutterTiming(line_time_s=self.line_time_s, exposure_s=cam.exposure_s, readout=cam.readout,
                                  rows=cam.roi.width if cam.readout == "columns" else cam.roi.height)
        t0 = c.timing.rs_trigger_s
        gs = GlobalShutterTiming(tuple(t - t0 for t in c.timing.gs_trigger_s), c.cameras.gs.exposure_s)
        return rs, gs, VideoGrid.covering(rs, gs, dt_s=rs.line_time_s * c.recon.grid_bin)

    def described(self, name: str) -> str:
        """'the calibration file's' etc.: where `name` came from, for messages."""
        return SOURCE_NAMES[self.sources[name]]

    def bundle_calibration(self) -> Calibration:
        """The bundle's calibration group: the resolved values and where each came from."""
        if self.psf is None:
            raise ConfigError(f"{self.rig.path}: calibration.psf: a PSF file is required for capture")
        extra = {"psf_crop": self.rig.config.calibration.psf.crop, "psf_spectral_support": spectral_support(self.psf),
                 **self.extra, "sources": dict(self.sources)}
        return Calibration(psf=self.psf.astype(np.float32), psf_source=self.psf_source, psf_bias=self.psf_bias,
                           gs_to_rs=self.gs_to_rs.copy(), white_balance=self.white_balance.copy(), extra=extra)


def resolve_psf_path(rig: Rig) -> Path:
    """The rig's PSF file: `package:NAME` is a file shipped in rngcam/data, a relative path is
    relative to the rig file."""
    cfg = rig.config.calibration.psf
    if cfg is None:
        raise ConfigError(f"{rig.path}: calibration.psf: a PSF file is required for capture")
    path = resolve_data_ref(cfg.path, rig.path.parent)
    if path.is_file():
        return path
    raise ConfigError(f"{rig.path}: calibration.psf.path: PSF file not found: {path} "
                      "(relative paths are relative to the rig file; package:NAME names a file in rngcam/data)")


def load_rig_psf(rig: Rig, channels: int | None = None) -> tuple[np.ndarray, str, float]:
    """(PSF (C, H, W) float64 summing to 1 per channel on the RS sensor grid, its file, bias)
    from the rig file; a one-channel PSF is repeated to `channels` when given."""
    cfg = rig.config.calibration.psf
    path = resolve_psf_path(rig)
    roi = rig.config.cameras.rs.roi
    shape = (roi.height, roi.width)
    try:
        raw = load_psf(path)
        if raw.shape[-2:] == shape and cfg.crop == 1.0:
            psf, bias = subtract_bias(raw, cfg.bias)  # already measured on this sensor grid
            psf = psf / psf.sum(axis=(-2, -1), keepdims=True)
        else:
            psf, bias = prepare_psf(raw, shape, crop=cfg.crop, bias=cfg.bias)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{rig.path}: calibration.psf: {path}: {exc}") from None
    if not np.all(np.isfinite(psf)):
        raise ConfigError(f"{rig.path}: calibration.psf: {path} has no usable signal")
    if channels is not None and psf.shape[0] == 1 and channels > 1:
        psf = np.repeat(psf, channels, axis=0)
    return psf, str(path), bias


def mock_sensor(cfg: CameraConfig) -> MockSensor | None:
    """The physics of a mock camera (its section, or the defaults); None for real hardware."""
    return (cfg.mock or MockSensor()) if cfg.backend == "mock" else None


def _mock_truth(rig: Rig) -> MockTruth | None:
    cams = rig.config.cameras
    sensors = {role: mock_sensor(getattr(cams, role)) for role in ROLES}
    if any(s is None for s in sensors.values()):
        return None
    rs_m, gs_m = sensors["rs"], sensors["gs"]
    h = np.eye(3)
    if gs_m.misalignment is not None:
        a = gs_m.misalignment
        centre = ((cams.gs.roi.width - 1) / 2, (cams.gs.roi.height - 1) / 2)
        h = similarity_matrix(a.shift_px, a.rotation_deg, a.scale, centre)
    g_gs = np.asarray(gs_m.channel_gain or [1.0] * 3, np.float64)
    g_rs = np.asarray(rs_m.channel_gain or [1.0] * 3, np.float64)
    scene = rig.config.mock or MockSceneConfig()
    if rs_m.line_time_s and scene.true_line_time_s and not math.isclose(rs_m.line_time_s, scene.true_line_time_s):
        raise ConfigError(f"{rig.path}: mock.true_line_time_s ({scene.true_line_time_s:g} s) and "
                          f"cameras.rs.mock.line_time_s ({rs_m.line_time_s:g} s) disagree: keep one")
    true_line = rs_m.line_time_s or scene.true_line_time_s or cams.rs.line_time_s
    return MockTruth(true_line, h, g_rs / g_gs, sensors, scene.readout_time_bias, scene.led_level)


def _line_time_note(stored, path, line_time_s, nominal_s, sources, progress) -> dict | None:
    """A calibrated line time replaces the rig's nominal one: say so, with how it was found."""
    if sources.get("line_time_s") != "calibration":
        return None
    method, u = stored.line_time_method, stored.line_time_uncertainty_s
    how = {"flicker": "measured from an LED's flicker", "readout": "SensorReadoutTime slope, a rough estimate",
           None: "method not recorded"}[method]
    shown = f"{line_time_s * 1e6:.4f} us" + (f" +- {u * 1e6:.4f}" if u is not None else "")
    progress(f"line time: {shown} from {Path(path).name} ({how}) replaces the rig's nominal "
             f"{nominal_s * 1e6:.4g} us")
    return {"method": method, "uncertainty_s": u, "nominal_s": nominal_s}


def resolve_rig(rig: Rig, progress: Progress = print, psf: bool = True,
                calibration_missing_ok: bool = False) -> ResolvedRig:
    """Merge the rig file, its calibration file and its mock sections (module doc). `psf`:
    load the rig's PSF (False: line time and features only). `calibration_missing_ok`: a
    calibration file the rig names but that does not exist yet is not an error (calibrate
    is about to write it)."""
    c = rig.config
    libraries.check_rig(rig)  # before anything is loaded or opened
    for line in rig.outside_warnings():
        progress(line)
    mock = _mock_truth(rig)
    sources: dict[str, str] = {}
    stored, stored_path = rig_calibration(rig, missing_ok=calibration_missing_ok)
    if stored is not None:
        progress(f"calibration: {', '.join(stored.parts()) or 'nothing'} from {stored_path}")

    def pick(name: str, stored_value, rig_value, default):
        if stored_value is not None:
            sources[name] = "calibration"
            return stored_value
        if rig_value is not None:
            sources[name] = "rig"
            return rig_value
        sources[name] = "default"
        return default

    line_time_s = float(pick("line_time_s", stored and stored.line_time_s, c.cameras.rs.line_time_s, math.nan))
    line_note = _line_time_note(stored, stored_path, line_time_s, c.cameras.rs.line_time_s, sources, progress)
    gs_to_rs = np.array(pick("gs_to_rs", stored and stored.gs_to_rs, c.calibration.gs_to_rs, np.eye(3)), np.float64)
    black = {}
    for role in ROLES:
        cfg = getattr(c.cameras, role)
        sensor = mock_sensor(cfg)
        black[role] = float(sensor.black_level_dn if sensor is not None else cfg.black_level_dn)
        sources[f"{role}_black_level_dn"] = "mock" if sensor is not None else "rig"
    out = ResolvedRig(rig=rig, line_time_s=line_time_s, gs_to_rs=gs_to_rs, white_balance=np.ones(0),
                      black_level_dn=black, sources=sources, calibration_file=stored_path, stored=stored,
                      mock=mock)
    if psf:
        channels = 3 if mock is not None else None  # mock cameras always deliver RGB
        out.rig_psf, path, bias = load_rig_psf(rig, channels)
        out.psf, out.psf_source, out.psf_bias = out.rig_psf, path, bias
        shown = Path(path).name
        sources["psf"] = "rig"
        if stored is not None and stored.psf is not None:
            p = stored.psf
            if p.shape[-2:] != out.rig_psf.shape[-2:]:
                p = resample(p, tuple(out.rig_psf.shape[-2:]))
            out.psf = normalise(np.clip(p, 0.0, None))
            out.psf_source = f"{stored_path} (rngcam calibrate psf)"
            out.psf_bias = float(stored.provenance.get("psf", {}).get("dark_level_dn", 0.0))
            sources["psf"] = "calibration"
            shown = stored_path.name
        progress(f"psf: {shown} ({sources['psf']}) -> "
                 f"{out.psf.shape[0]}x{out.psf.shape[1]}x{out.psf.shape[2]} on the RS grid "
                 f"(crop {c.calibration.psf.crop:g}, bias {out.psf_bias:g}); spectral support "
                 f"{spectral_support(out.psf):.2%} of frequencies above 10% of DC")
    channels = out.psf.shape[0] if out.psf is not None else 3
    out.white_balance = np.array(pick("white_balance", stored and stored.white_balance,
                                      c.calibration.white_balance, np.ones(channels)), np.float64)
    out.sources = {k: sources[k] for k in SOURCE_ORDER if k in sources}
    if stored is not None:
        found = ("the rig's calibration.file" if c.calibration.file else
                 "beside the rig file (<rig>.calib.h5, the rule when the rig names none)")
        out.extra = {"calibration_file": str(stored_path), "calibration_found": found,
                     "calibration_parts": stored.parts(),
                     "calibration_provenance": {k: v for k, v in stored.provenance.items() if k in stored.parts()}}
    if line_note:
        out.extra["line_time"] = line_note
    return out
