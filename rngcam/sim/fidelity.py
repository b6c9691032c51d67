"""Capture families finer than the reconstruction's grid (`rngcam simulate --fidelity`).

- grid: the truth on the grid, measured with the operators the reconstruction inverts (an
  inverse crime, kept as the default for the existing benchmarks).
- fine: the truth rendered at SPACE x the grid in space and TIME x in time and measured there,
  as the rig measures: the sensors have SPACE x the grid's pixels along each side, each RS sensor
  row with its own start time (line time = grid dt / SPACE), and the bundle holds those frames
  with grid_bin SPACE, so the reconstruction bins them as it bins the rig's (16 there): each grid
  row the mean of SPACE sensor rows (a trapezoid in time), each grid pixel of SPACE x SPACE
  sensor pixels. The PSF is the physical PSF at the sensor's resolution. The truth is the fine
  render's mean over each grid pixel and frame. Calibration handed over is exact.
- lab: fine plus every calibration error, drawn from the seed at the size the project's own
  calibration reports with a margin (LAB_MAGNITUDES): a GS-to-RS similarity (sub-pixel shift,
  rotation, scale) and radial GS lens distortion; PSF measurement noise and background; a
  line-time error; GS/RS colour gains and GS vignetting; hot and dead pixels on both sensors.

The true values go to the bundle's meta["truth_calibration"] (GS-to-RS in grid pixels, with the
convention of rngcam.recon.methods.selfcal: the GS camera sees the scene at S(p), p a GS pixel).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
import torch

from rngcam.physics.geometry import similarity_matrix
from rngcam.physics.operators import GlobalShutter, rolling_shutter_for
from rngcam.physics.psf import magnify
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid

FIDELITIES = ("grid", "fine", "lab")
SPACE = 2  # sensor pixels per grid pixel along each side (the lab rig: 16)
TIME = 4  # sub-frames per grid frame

# Sizes of the calibration errors of `lab`, each with where the figure comes from.
LAB_MAGNITUDES = {
    # calibrate align reports a 0.28 px median local shift on the mock rig: 0.4 px with a margin
    "shift_px": 0.4,
    "rotation_deg": 0.3,  # 0.17 px at the edge of a 64 px grid: within align's residual
    "scale": 0.004,  # relative, 0.13 px at the edge of a 64 px grid
    "distortion_k1": 0.004,  # radial, 0.25 px at a 64 px grid's corners (align fits a homography only)
    # calibrate psf refuses a peak SNR under 10 and warns under 50: noise at 1 % of the peak (SNR 100);
    # it subtracts a dark frame: a residual background of 0.1 % of the peak (1.5 % of the PSF's sum)
    "psf_noise": 0.01,
    "psf_background": 0.001,
    "line_time": 0.005,  # relative; calibrate linetime fits the slope of readout times
    "gain": 0.03,  # GS/RS per channel (calibrate whitebalance from one grey card)
    "vignetting": 0.04,  # GS falloff at the corners, not calibrated at all
    "hot_fraction": 0.001,  # of the pixels, each sensor: a dark-current offset of 200-1500 DN
    "dead_fraction": 0.0005,  # of the pixels, each sensor: reads the black level
}
# The same after the project's calibrations, each measured against the mock rig's truth, with a margin of
# about 2x: `calibrate align` on a static chart (shift 0.023 px, rotation 0.005 deg, scale 0.0007 off),
# `calibrate linetime --flicker` (within 0.014 % at -3 % to +3 %; bench/linetime.md) and `calibrate psf`
# (peak SNR 1448 from its 16 frames: noise 0.07 % of the peak). What none measures (distortion, the PSF's
# residual background, gains, vignetting, defects) stays at the lab family's size.
CALIBRATED_MAGNITUDES = {**LAB_MAGNITUDES, "shift_px": 0.05, "rotation_deg": 0.02, "scale": 0.001,
                         "line_time": 0.0005, "psf_noise": 0.0015}


@dataclass
class LabErrors:
    """One draw of the calibration errors (values as the rig has them, not as calibrated)."""

    shift_px: tuple[float, float] = (0.0, 0.0)  # (x, y), grid pixels
    rotation_deg: float = 0.0
    scale: float = 1.0
    distortion_k1: float = 0.0  # r' = r (1 + k1 r^2), r relative to the half diagonal
    psf_noise: float = 0.0
    psf_background: float = 0.0
    psf_scale: float = 1.0  # the handed-over PSF's size / the true one's (a scene at another depth)
    line_time_scale: float = 1.0  # true line time / recorded line time
    gs_gains: tuple[float, float, float] = (1.0, 1.0, 1.0)  # GS signal / RS signal, per channel
    vignetting: float = 0.0
    hot_fraction: float = 0.0
    dead_fraction: float = 0.0

    @classmethod
    def draw(cls, seed: int, magnitudes: dict | None = None) -> LabErrors:
        """Magnitudes from `magnitudes` (LAB_MAGNITUDES), directions and signs from the seed."""
        m = LAB_MAGNITUDES if magnitudes is None else magnitudes
        rng = np.random.default_rng([seed, 30])
        angle = rng.uniform(0, 2 * np.pi)
        sign = lambda: float(rng.choice([-1.0, 1.0]))  # noqa: E731
        gains = 1 + m["gain"] * rng.choice([-1.0, 1.0], 3) * rng.uniform(0.5, 1.0, 3)
        return cls(shift_px=(m["shift_px"] * float(np.cos(angle)), m["shift_px"] * float(np.sin(angle))),
                   rotation_deg=sign() * m["rotation_deg"], scale=1 + sign() * m["scale"],
                   distortion_k1=m["distortion_k1"], psf_noise=m["psf_noise"],
                   psf_background=m["psf_background"], line_time_scale=1 + sign() * m["line_time"],
                   gs_gains=tuple(float(g) for g in gains), vignetting=m["vignetting"],
                   hot_fraction=m["hot_fraction"], dead_fraction=m["dead_fraction"])

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


def bin_space(img: np.ndarray, factor: int = SPACE) -> np.ndarray:
    """Mean over factor x factor blocks of the last two axes."""
    *lead, h, w = img.shape
    return img.reshape(*lead, h // factor, factor, w // factor, factor).mean(axis=(-3, -1))


def bin_time(video: np.ndarray, frames: int, factor: int = TIME) -> np.ndarray:
    """(C, frames * factor + extra, H, W) -> (C, frames, H, W): the mean of each grid frame's sub-frames."""
    c, _, h, w = video.shape
    return video[:, :frames * factor].reshape(c, frames, factor, h, w).mean(axis=2)


def fine_grid(grid: VideoGrid, line_time_scale: float, last_start_s: float, exposure_s: float) -> VideoGrid:
    """The sub-frame grid: TIME x the grid's frames, more if a longer true line time needs them
    (`last_start_s`: the last sensor row's start at the recorded line time)."""
    end = last_start_s * line_time_scale + exposure_s
    n = max(grid.n_frames * TIME, int(np.ceil(end / (grid.dt_s / TIME) - 1e-9)))
    return VideoGrid(grid.dt_s / TIME, n)


def similarity_map(shape: tuple[int, int], errors: LabErrors, factor: int = SPACE) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps on a `factor`x finer pixel grid: GS sensor pixel p samples the scene at
    S(D(p)), S and D in grid pixel coordinates about the image centre (module docstring)."""
    h, w = shape  # fine pixels
    hg, wg = h / factor, w / factor
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (xx + 0.5) / factor - wg / 2  # grid px from the centre
    y = (yy + 0.5) / factor - hg / 2
    r2 = (x ** 2 + y ** 2) / ((wg / 2) ** 2 + (hg / 2) ** 2)
    x, y = x * (1 + errors.distortion_k1 * r2), y * (1 + errors.distortion_k1 * r2)
    th = np.deg2rad(errors.rotation_deg)
    xs = errors.scale * (np.cos(th) * x - np.sin(th) * y) + errors.shift_px[0] + wg / 2
    ys = errors.scale * (np.sin(th) * x + np.cos(th) * y) + errors.shift_px[1] + hg / 2
    return (xs * factor - 0.5).astype(np.float32), (ys * factor - 0.5).astype(np.float32)


def true_gs_to_rs(truth: dict, sensor_shape: tuple[int, int], factor: int = SPACE) -> np.ndarray:
    """The bundle's true GS-to-RS homography (raw GS sensor pixel -> raw RS sensor pixel, pixel centres at
    integers) from its meta["truth_calibration"] (`similarity_map`'s S about the grid's centre; the radial
    distortion, which no homography holds, left out): what a perfect `calibrate align` would hand over."""
    h, w = sensor_shape
    shift = factor * np.asarray(truth["shift_px"], np.float64)  # grid pixels -> sensor pixels
    return similarity_matrix(shift, truth.get("rotation_deg", 0.0), truth.get("scale", 1.0), ((w - 1) / 2, (h - 1) / 2))


def vignetting_field(shape: tuple[int, int], amount: float) -> np.ndarray:
    """1 at the centre falling quadratically to 1 - amount at the corners, (H, W)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    return 1 - amount * r2


def fine_measure(video: np.ndarray, psf_fine: np.ndarray, grid: VideoGrid, fgrid: VideoGrid,
                 line_time_s: float, exposure_s: float, gs: GlobalShutterTiming,
                 errors: LabErrors, readout: str = "top-down") -> tuple[np.ndarray, np.ndarray]:
    """Noiseless RS (C, Hs, Ws) and GS (C, G, Hs, Ws) at the sensors' resolution, in the grid's
    operator units, from a video (C, Kf, Hs, Ws) on the sub-frame grid `fgrid` (Hs = SPACE H);
    `line_time_s` is a sensor row's, as recorded (the true one is errors.line_time_scale x it);
    `readout` the RS readout order (physics.timing.READOUTS)."""
    v = torch.from_numpy(np.asarray(video, np.float64))
    c, _, hf, wf = v.shape
    true_line = line_time_s * errors.line_time_scale
    rs_t = RollingShutterTiming(line_time_s=true_line, exposure_s=exposure_s,
                                rows=wf if readout == "columns" else hf, readout=readout)
    units = fgrid.dt_s / grid.dt_s  # operator units count exposure in frames of the grid
    rs = rolling_shutter_for(torch.from_numpy(psf_fine), torch.from_numpy(rs_t.weights(fgrid)), (hf, wf),
                             channels=c, transposed=rs_t.transposed).A(v).numpy() * units
    gs_img = GlobalShutter(torch.from_numpy(gs.weights(fgrid)), c, (hf, wf)).A(v).numpy() * units
    if errors != LabErrors():
        mx, my = similarity_map((hf, wf), errors)  # float32
        vig = vignetting_field((hf, wf), errors.vignetting)
        gains = np.asarray(errors.gs_gains, np.float64)
        for g in range(gs_img.shape[1]):
            for ch in range(c):
                # float32: OpenCV 5.0's bicubic remap of float64 images writes wrong values at
                # hundreds of pixels per frame (tests/test_sim_fidelity.py)
                warped = cv2.remap(gs_img[ch, g].astype(np.float32), mx, my,
                                   cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT).astype(np.float64)
                gs_img[ch, g] = np.clip(warped, 0, None) * vig * gains[ch]
    return rs, gs_img


def psf_measured(psf_sensor: np.ndarray, errors: LabErrors, seed: int) -> np.ndarray:
    """The PSF as calibration hands it over: magnified by `psf_scale` (rngcam.physics.psf.magnify),
    noise and a background relative to the peak (float32)."""
    if errors.psf_scale != 1:
        psf_sensor = magnify(psf_sensor, errors.psf_scale).astype(np.float32)
    if errors.psf_noise == 0 and errors.psf_background == 0:
        return psf_sensor
    rng = np.random.default_rng([seed, 31])
    peak = psf_sensor.max(axis=(-2, -1), keepdims=True)
    noisy = psf_sensor + peak * (errors.psf_background + errors.psf_noise * rng.standard_normal(psf_sensor.shape))
    return np.clip(noisy, 0, None).astype(np.float32)


def pixel_defects(frames: np.ndarray, errors: LabErrors, max_dn: int, black_dn: float, seed: int,
                  camera: int) -> tuple[np.ndarray, dict]:
    """Hot pixels (a dark-current offset of 200-1500 DN, fixed over frames) and dead ones (the
    black level) at fixed places of a camera's frames (F, H, W, C) uint16."""
    if errors.hot_fraction == 0 and errors.dead_fraction == 0:
        return frames, {"hot": [], "dead": []}
    rng = np.random.default_rng([seed, 32, camera])
    _, h, w, _ = frames.shape
    n_hot, n_dead = (max(1, round(f * h * w)) for f in (errors.hot_fraction, errors.dead_fraction))
    places = rng.choice(h * w, size=n_hot + n_dead, replace=False)
    hot, dead = places[:n_hot], places[n_hot:]
    out = frames.astype(np.int64)
    offsets = rng.uniform(200, 1500, n_hot)
    for p, off in zip(hot, offsets, strict=True):
        out[:, p // w, p % w] += int(off)
    for p in dead:
        out[:, p // w, p % w] = int(round(black_dn))
    listed = {k: [[int(p // w), int(p % w)] for p in v] for k, v in (("hot", hot), ("dead", dead))}
    return np.clip(out, 0, max_dn).astype(frames.dtype), listed
