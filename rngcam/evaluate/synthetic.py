"""Small synthetic captures for the stress matrix: a moving square, a PSF, exact timing.

`CaptureSpec` describes one capture (image size, RS/GS timing in line times, PSF kind,
brightness); `make_problem` measures the scene noiselessly through the physics (a Problem with
truth) and `make_bundle` writes a real capture bundle through the sensor model, so cases
about the data (dark, saturated, NaN frames) go through the same path as a user's capture.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from rngcam.formats.bundle import Bundle, Calibration, CameraRecord, Truth, write_bundle
from rngcam.paths import MEASURED_PSF, package_data
from rngcam.physics import psf as psf_mod
from rngcam.physics.sensor import SensorModel
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid
from rngcam.recon.problem import Problem, problem_from_video

PSF_KINDS = ("delta", "flat", "caustic", "real")


@dataclass(frozen=True)
class CaptureSpec:
    """One synthetic capture. Times are in RS line times; the grid has one frame per line
    unless `frame_lines` says otherwise (then a frame lasts that many line times)."""

    height: int = 12
    width: int = 12
    channels: int = 3
    exposure_lines: float = 6.0
    gs_frames: int = 3
    gs_exposure_lines: float = 1.0
    psf: str = "caustic"
    brightness: float = 1.0
    frame_lines: float | None = None
    line_time_s: float = 1e-5
    seed: int = 0

    def with_(self, **changes) -> CaptureSpec:
        return replace(self, **changes)


def timings(spec: CaptureSpec) -> tuple[RollingShutterTiming, GlobalShutterTiming, VideoGrid]:
    """RS timing, GS timing (key frames spread over the capture) and the grid covering both."""
    lt = spec.line_time_s
    rs = RollingShutterTiming(line_time_s=lt, exposure_s=spec.exposure_lines * lt, rows=spec.height)
    dt = None if spec.frame_lines is None else spec.frame_lines * lt
    span = VideoGrid.covering(rs, None, dt_s=dt)
    gs_exp = min(spec.gs_exposure_lines * lt, span.n_frames * span.dt_s)
    n = max(1, min(spec.gs_frames, span.n_frames))
    last = max(span.n_frames * span.dt_s - gs_exp, 0.0)
    triggers = np.linspace(0.0, last, n) if n > 1 else np.zeros(1)
    gs = GlobalShutterTiming(trigger_s=tuple(triggers), exposure_s=gs_exp)
    return rs, gs, VideoGrid.covering(rs, gs, dt_s=dt)


def moving_square(channels: int, frames: int, height: int, width: int, brightness: float = 1.0,
                  seed: int = 0) -> np.ndarray:
    """(C, K, H, W) float64: a bright square crossing a soft coloured gradient, times `brightness`."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width] / max(height, width, 2)
    tint = 0.2 + 0.3 * rng.random(channels)
    background = tint[:, None, None] * (0.6 + 0.4 * (x + y)[None]) + 0.05 * rng.random((channels, height, width))
    video = np.repeat(background[:, None], frames, axis=1)
    side = max(1, min(height, width) // 3)
    for k in range(frames):
        x0 = round((width - side) * (k / max(frames - 1, 1)))
        y0 = (height - side) // 2
        video[:, k, y0:y0 + side, x0:x0 + side] = 0.9
    return np.clip(video, 0, 1) * brightness


def make_psf(kind: str, height: int, width: int, seed: int = 0) -> np.ndarray:
    """(1, Hp, Wp) PSF summing to 1: a delta (identity), flat (a box: rank-deficient, every
    image with the same sum looks alike), caustic (sparse random bright points, slightly
    blurred) or real (the measured DiffuserCam tutorial PSF in rngcam/data, resampled)."""
    if kind == "delta":
        return np.ones((1, 1, 1))
    if kind == "flat":
        return np.full((1, height, width), 1.0 / (height * width))
    if kind == "caustic":
        rng = np.random.default_rng(seed)
        img = np.zeros((height, width))
        n = max(1, height * width // 12)
        img[rng.integers(0, height, n), rng.integers(0, width, n)] = rng.random(n) + 0.5
        img = cv2.GaussianBlur(img, (3, 3), 0.6)
        return (img / img.sum())[None]
    if kind == "real":
        raw = psf_mod.load_psf(package_data(MEASURED_PSF))
        psf, _ = psf_mod.prepare_psf(raw, (height, width), crop=0.5, bias="auto")
        return psf.mean(axis=0, keepdims=True) / psf.mean(axis=0).sum()
    raise ValueError(f"unknown PSF kind {kind!r}; choose one of {PSF_KINDS}")


def make_problem(spec: CaptureSpec) -> Problem:
    """A noiseless Problem (float64, with truth) for `spec`."""
    rs, gs, grid = timings(spec)
    video = moving_square(spec.channels, grid.n_frames, spec.height, spec.width, spec.brightness, spec.seed)
    psf = make_psf(spec.psf, spec.height, spec.width, spec.seed)
    dt = None if spec.frame_lines is None else grid.dt_s
    return problem_from_video(torch.from_numpy(video), torch.from_numpy(psf), rs, gs, dt_s=dt)


FrameHook = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def make_bundle(spec: CaptureSpec, path: Path, noise: bool = True, tamper: FrameHook | None = None) -> Path:
    """Write a capture bundle (RGB12 frames through the sensor model, PSF, truth) for `spec`.

    `tamper(rs_frames, gs_frames) -> (rs_frames, gs_frames)` may alter the raw frames before
    writing (e.g. float frames with NaN)."""
    if spec.frame_lines is not None:
        raise ValueError("bundles use one grid frame per line time (frame_lines=None)")
    rs, gs, grid = timings(spec)
    video = moving_square(spec.channels, grid.n_frames, spec.height, spec.width, spec.brightness, spec.seed)
    psf = make_psf(spec.psf, spec.height, spec.width, spec.seed)
    return write_capture(video, psf, rs, gs, grid, path, noise=noise, seed=spec.seed, tamper=tamper,
                         source="rngcam bench --stress")


def write_capture(video: np.ndarray, psf: np.ndarray, rs: RollingShutterTiming, gs: GlobalShutterTiming,
                  grid: VideoGrid, path: Path, noise: bool = True, seed: int = 0,
                  tamper: FrameHook | None = None, source: str = "rngcam bench") -> Path:
    """Measure `video` (C, K, H, W) through the physics and a 12-bit sensor; write the bundle
    (frames, timing, PSF, truth) to `path` (replacing it)."""
    problem = problem_from_video(torch.from_numpy(np.asarray(video, np.float64)), torch.from_numpy(psf),
                                 rs, gs)
    sensor = SensorModel(bit_depth=12, black_level_dn=64.0, full_well_e=10_000.0, read_noise_e=3.0)
    rng = np.random.default_rng(seed)
    dt = grid.dt_s
    rs_frames = sensor.capture(problem.b_rs.numpy(), rs.exposure_s, dt, rng, noise)[None]
    gs_frames = np.stack([sensor.capture(problem.b_gs[:, g].numpy(), gs.exposure_s, dt, rng, noise)
                          for g in range(problem.b_gs.shape[1])])
    if tamper is not None:
        rs_frames, gs_frames = tamper(rs_frames, gs_frames)

    def camera(frames, exposure_s, triggers, line_time_s=None):
        return CameraRecord(frames=frames, pixel_format=sensor.pixel_format, bit_depth=sensor.bit_depth,
                            black_level_dn=sensor.black_level_dn, exposure_s=exposure_s,
                            trigger_times_s=np.asarray(triggers, float), line_time_s=line_time_s,
                            model="synthetic")

    bundle = Bundle(
        rs=camera(rs_frames, rs.exposure_s, [0.0], rs.line_time_s),
        gs=camera(gs_frames, gs.exposure_s, gs.trigger_s),
        calibration=Calibration(psf=problem.psf.numpy().astype(np.float32), psf_source="synthetic"),
        truth=Truth(video=problem.truth.numpy().astype(np.float32), frame_times_s=grid.centres_s(), dt_s=dt),
        meta={"grid_bin": 1, "source": source},
    )
    return write_bundle(bundle, path, overwrite=True)
