"""PSF from frames of a point source on the RS camera.

Average N raw frames, subtract a dark frame (the mean of frames taken with the source off) or
the camera's black level, refuse saturated frames, measure the signal-to-noise ratio, and
normalise each channel to sum 1 (rngcam.physics.psf's convention). Bayer frames are binned
2x2 per colour (as the reconstruction does), so a Bayer PSF is (3, H/2, W/2); capture
resamples a stored PSF to the RS sensor grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rngcam.errors import RngcamError
from rngcam.physics.psf import figure_line, normalise, resample, resolvable_fraction, snr_of_mean_signal
from rngcam.physics.sensor import BAYER_FORMATS, demosaic_bin

MIN_SNR = 10.0  # below this the PSF is refused
WARN_SNR = 50.0  # below this a warning suggests more frames or a brighter source


class PsfCalibrationError(RngcamError):
    """The point-source frames cannot give a usable PSF."""


@dataclass
class PsfEstimate:
    """psf: (C, H, W) float64, sums to 1 per channel. peak_snr: peak of the averaged,
    dark-subtracted image over the noise of that average. peak_fraction: its peak in units of
    the sensor's full scale above black."""

    psf: np.ndarray
    frames: int
    dark: str
    dark_level_dn: float
    peak_snr: float
    peak_fraction: float
    saturated_pixels: int
    mosaic: int
    warnings: list[str] = field(default_factory=list)


def _chw(frame: np.ndarray, pixel_format: str) -> np.ndarray:
    frame = np.asarray(frame)
    if pixel_format in BAYER_FORMATS:
        return demosaic_bin(frame).astype(np.float64)
    if frame.ndim == 3:
        return np.moveaxis(frame, -1, 0).astype(np.float64)
    if frame.ndim == 2:
        return frame[None].astype(np.float64)
    raise PsfCalibrationError(f"a camera frame must be (H, W) or (H, W, C), got shape {frame.shape}")


def _haar_noise(img: np.ndarray) -> float:
    """Robust per-pixel noise std of a (C, H, W) image from 2x2 diagonal Haar details (MAD)."""
    h, w = (img.shape[-2] // 2) * 2, (img.shape[-1] // 2) * 2
    x = img[..., :h, :w]
    d = (x[..., 0::2, 0::2] - x[..., 1::2, 0::2] - x[..., 0::2, 1::2] + x[..., 1::2, 1::2]) / 2
    return float(np.median(np.abs(d - np.median(d)))) / 0.6745


def estimate_psf(frames, pixel_format: str, bit_depth: int, black_level_dn: float,
                 dark_frames=None, max_saturated: int = 0) -> PsfEstimate:
    """The PSF from raw point-source `frames` (N of (H, W) or (H, W, C)); see module docstring.

    Dark: the mean of `dark_frames` when given, else the constant `black_level_dn`. Raises
    PsfCalibrationError when more than `max_saturated` pixels reach full scale in any frame,
    when the SNR is below MIN_SNR, or when there is no signal.
    """
    frames = [np.asarray(f) for f in frames]
    if not frames:
        raise PsfCalibrationError("no point-source frames")
    max_dn = 2 ** int(bit_depth) - 1
    saturated = int(max(np.count_nonzero(f >= max_dn) for f in frames))
    if saturated > max_saturated:
        raise PsfCalibrationError(f"{saturated} pixel(s) saturated in a point-source frame; lower the "
                                  "exposure, the gain or the source brightness")
    stack = np.stack([_chw(f, pixel_format) for f in frames])
    mean = stack.mean(axis=0)
    if dark_frames is not None and len(dark_frames):
        dark = np.stack([_chw(f, pixel_format) for f in dark_frames]).mean(axis=0)
        if dark.shape != mean.shape:
            raise PsfCalibrationError(f"dark frames are {dark.shape}, point-source frames {mean.shape}")
        dark_text, dark_level = f"dark frame (mean of {len(dark_frames)})", float(dark.mean())
        n_dark = len(dark_frames)
    else:
        dark = np.full_like(mean, float(black_level_dn))
        dark_text, dark_level, n_dark = f"black level {black_level_dn:g} DN", float(black_level_dn), 0
    signal = mean - dark
    # Noise of the averaged image: per-pixel temporal spread when there are several frames.
    if len(frames) > 1:
        noise = float(np.median(stack.std(axis=0, ddof=1))) / np.sqrt(len(frames))
    else:
        noise = _haar_noise(signal)
    if n_dark:
        noise *= np.sqrt(1 + len(frames) / n_dark)  # the dark estimate adds its own noise
    peak = float(signal.max())
    if not np.isfinite(peak) or peak <= 0:
        raise PsfCalibrationError("no signal above the dark level: is the point source on and in view?")
    snr = peak / max(noise, 1e-12)
    if snr < MIN_SNR:
        raise PsfCalibrationError(f"PSF signal-to-noise ratio {snr:.1f} is below {MIN_SNR:g}; use more "
                                  "frames, a longer exposure or a brighter source")
    warnings = []
    if snr < WARN_SNR:
        warnings.append(f"PSF signal-to-noise ratio is only {snr:.1f}; more frames or a brighter "
                        "source would help")
    peak_fraction = peak / (max_dn - float(black_level_dn))
    if peak_fraction < 0.2:
        warnings.append(f"the PSF peak uses only {peak_fraction:.0%} of the sensor's range; a longer "
                        "exposure would raise the SNR")
    try:
        psf = normalise(np.clip(signal, 0.0, None))
    except ValueError as exc:
        raise PsfCalibrationError(str(exc)) from None
    return PsfEstimate(psf=psf, frames=len(frames), dark=dark_text, dark_level_dn=dark_level,
                       peak_snr=float(snr), peak_fraction=float(peak_fraction),
                       saturated_pixels=saturated,
                       mosaic=2 if pixel_format in BAYER_FORMATS else 1, warnings=warnings)


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two equally shaped arrays (e.g. an estimated and a true PSF)."""
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    a, b = a - a.mean(), b - b.mean()
    return float((a @ b) / np.sqrt((a @ a) * (b @ b)))


FIGURE_CONTRAST = 0.1  # the PSF figure counts frequencies that carry a 10 % contrast pattern


def frame_snr(frame: np.ndarray, pixel_format: str, black_level_dn: float) -> float:
    """Per-pixel signal-to-noise of one raw frame: its mean above black over its noise
    (estimated from the frame itself, 2x2 Haar details; Bayer frames binned per colour first)."""
    img = _chw(frame, pixel_format) - float(black_level_dn)
    noise = max(_haar_noise(img), 1 / np.sqrt(12))  # never below the quantisation noise
    return max(float(img.mean()), 0.0) / noise


def psf_figure(psf: np.ndarray, snr_px: float, shape: tuple[int, int] | None = None) -> tuple[float, str]:
    """(fraction, report line): the PSF (resampled to `shape` when given) against the RS noise
    floor of per-pixel SNR `snr_px` (rngcam.physics.psf.resolvable_fraction)."""
    psf = np.clip(np.nan_to_num(np.asarray(psf, np.float64)), 0, None)
    if shape is not None and psf.shape[-2:] != tuple(shape):
        psf = resample(psf, tuple(shape))
    fraction = resolvable_fraction(psf, snr_px, FIGURE_CONTRAST)
    return fraction, figure_line(fraction, snr_px, FIGURE_CONTRAST)


def bundle_psf_figure(path) -> str:
    """The PSF figure of a capture bundle, at the noise floor of its own RS image."""
    from rngcam.formats.bundle import read_bundle  # heavy: bundle loads h5py, torch

    b = read_bundle(path)
    if b.calibration is None or b.calibration.psf is None or b.rs is None:
        return "PSF figure: no PSF or no RS image in this bundle"
    frame = np.asarray(b.rs.frames[0])
    snr = frame_snr(frame, b.rs.pixel_format, b.rs.black_level_dn)
    shape = _chw(frame, b.rs.pixel_format).shape[-2:]
    return psf_figure(b.calibration.psf, snr, shape)[1]


def rig_snr(camera) -> tuple[float, str]:
    """(per-pixel SNR, how it was set) of an RS image at half full scale for a rig's camera
    config: its mock sensor's full well and read noise, else a typical 10,000 e- / 3 e- sensor."""
    mock = getattr(camera, "mock", None)
    full_well, read = (mock.full_well_e, mock.read_noise_e) if mock is not None else (10_000.0, 3.0)
    how = "mock sensor" if mock is not None else "assumed sensor"
    return (snr_of_mean_signal(full_well / 2, read),
            f"scene at half full scale, {how} of {full_well:g} e- full well, {read:g} e- read noise")
