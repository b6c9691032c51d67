"""PSF handling: load, subtract bias, resample to the grid by area averaging, normalise.

Normalisation convention: each channel of the PSF sums to 1. A spatially uniform scene of
intensity I, far from the image borders, then gives a convolved image of intensity I, so the
RS measurement of a static scene is I * exposure_s / dt, the same scale as the GS camera.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

SUFFIXES = (".tif", ".tiff", ".png", ".npy", ".h5", ".hdf5")


def load_psf(path: str | Path) -> np.ndarray:
    """Read a PSF image as float64 (C, H, W); colour files are returned RGB."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PSF file not found: {path}")
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        import tifffile

        arr = tifffile.imread(path)
    elif suffix == ".png":
        arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise ValueError(f"cannot decode PNG PSF: {path}")
        if arr.ndim == 3:
            arr = cv2.cvtColor(arr[..., :3], cv2.COLOR_BGR2RGB)
    elif suffix == ".npy":
        arr = np.load(path)
    elif suffix in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "r") as f:
            for name in ("psf", "calibration/psf"):
                if name in f:
                    arr = f[name][()]
                    break
            else:
                raise ValueError(f"no 'psf' or 'calibration/psf' dataset in {path}")
    else:
        raise ValueError(f"unsupported PSF format {suffix!r} (use one of {', '.join(SUFFIXES)})")
    return as_chw(np.asarray(arr, dtype=np.float64))


def as_chw(arr: np.ndarray) -> np.ndarray:
    """(H, W) -> (1, H, W); (H, W, C) with C <= 4 -> (C, H, W); (C, H, W) unchanged."""
    if arr.ndim == 2:
        return arr[None]
    if arr.ndim == 3 and arr.shape[-1] in (1, 3, 4) and arr.shape[0] not in (1, 3):
        return np.moveaxis(arr[..., :3] if arr.shape[-1] == 4 else arr, -1, 0)
    if arr.ndim == 3:
        return arr
    raise ValueError(f"a PSF must be 2-D or 3-D, got shape {arr.shape}")


def estimate_bias(psf: np.ndarray, patch: int = 10) -> float:
    """Dark level: the median of the four corner patches (the caustic rarely reaches them)."""
    p = min(patch, psf.shape[-2] // 4 or 1, psf.shape[-1] // 4 or 1)
    corners = [psf[..., :p, :p], psf[..., :p, -p:], psf[..., -p:, :p], psf[..., -p:, -p:]]
    return float(np.median(np.concatenate([c.ravel() for c in corners])))


def subtract_bias(psf: np.ndarray, bias: float | str | None = "auto") -> tuple[np.ndarray, float]:
    """Subtract a dark level ('auto' estimates it), clip at zero; returns (psf, bias used)."""
    if bias is None:
        bias = 0.0
    elif bias == "auto":
        bias = estimate_bias(psf)
    return np.clip(psf - float(bias), 0.0, None), float(bias)


def crop_centre(psf: np.ndarray, fraction: float, aspect: float) -> np.ndarray:
    """Central crop keeping `fraction` of the limiting side, with height/width = aspect."""
    if not 0 < fraction <= 1:
        raise ValueError(f"crop fraction must be in (0, 1], got {fraction}")
    h, w = psf.shape[-2:]
    ch = h * fraction
    cw = ch / aspect
    if cw > w * fraction:
        cw = w * fraction
        ch = cw * aspect
    ch, cw = max(1, int(round(ch))), max(1, int(round(cw)))
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    return psf[..., y0:y0 + ch, x0:x0 + cw]


def resample(psf: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area-average (C, H, W) to (C, *shape) (cv2.INTER_AREA; exact box means for integer factors)."""
    out = [cv2.resize(c.astype(np.float64), (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
           for c in psf]
    return np.stack(out)


def normalise(psf: np.ndarray) -> np.ndarray:
    """Scale each channel to sum 1; a PSF with no signal is an error, not a NaN."""
    sums = psf.sum(axis=(-2, -1), keepdims=True)
    if not np.all(np.isfinite(psf)) or np.any(sums <= 0):
        raise ValueError("PSF has no positive signal after bias subtraction (or is not finite)")
    return psf / sums


def spectral_support(psf: np.ndarray, threshold: float = 0.1) -> float:
    """Fraction of the PSF's 2-D frequencies whose magnitude exceeds `threshold` x DC.

    A caustic PSF that survives sampling keeps a broad spectrum; an area-downsampled blob keeps
    almost none, and the RS image then carries little detail about the scene.
    """
    mono = np.asarray(psf, dtype=np.float64).reshape(-1, *psf.shape[-2:]).mean(axis=0)
    spec = np.abs(np.fft.rfft2(mono))
    dc = spec[0, 0]
    if dc <= 0:
        return 0.0
    return float((spec > threshold * dc).mean())


def prepare_psf(psf: np.ndarray, shape: tuple[int, int], crop: float = 1.0,
                bias: float | str | None = "auto", channels: int | None = None) -> tuple[np.ndarray, float]:
    """Bias-subtract, crop the centre `crop` fraction, area-resample to `shape`, normalise.

    Returns (psf (C, *shape) float64 summing to 1 per channel, bias used). With `channels`,
    a mono PSF is repeated to that many channels.
    """
    psf, used = subtract_bias(as_chw(np.asarray(psf, dtype=np.float64)), bias)
    psf = resample(crop_centre(psf, crop, shape[0] / shape[1]), shape)
    psf = normalise(psf)
    if channels is not None and psf.shape[0] != channels:
        if psf.shape[0] != 1:
            raise ValueError(f"cannot map a {psf.shape[0]}-channel PSF to {channels} channels")
        psf = np.repeat(psf, channels, axis=0)
    return psf, used
