"""PSF handling: load, subtract bias, resample to the grid by area averaging, normalise.

Normalisation convention: each channel of the PSF sums to 1. A spatially uniform scene of
intensity I, far from the image borders, then gives a convolved image of intensity I, so the
RS measurement of a static scene is I * exposure_s / dt, the same scale as the GS camera.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import cv2
import numpy as np

from rngcam.untrusted import read_untrusted

SUFFIXES = (".tif", ".tiff", ".png", ".npy", ".h5", ".hdf5")
MAX_PSF_FILE_BYTES = 1 << 30  # a raw PSF image of a large sensor in float64 is a few hundred MB


def load_psf(path: str | Path) -> np.ndarray:
    """Read a PSF image as float64 (C, H, W); colour files are returned RGB."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PSF file not found: {path}")
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff", ".png", ".npy"):
        # a rig's PSF file may come from elsewhere: read by descriptor (no link, FIFO or device), bounded
        data = read_untrusted(path, MAX_PSF_FILE_BYTES, what="PSF file")
    if suffix in (".tif", ".tiff"):
        import tifffile  # heavy: tifffile

        arr = tifffile.imread(io.BytesIO(data))
    elif suffix == ".png":
        arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise ValueError(f"cannot decode PNG PSF: {path}")
        if arr.ndim == 3:
            arr = cv2.cvtColor(arr[..., :3], cv2.COLOR_BGR2RGB)
    elif suffix == ".npy":
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    elif suffix in (".h5", ".hdf5"):
        # a rig's PSF file may come from elsewhere: no links, sizes checked
        from rngcam import h5safe  # heavy: h5safe loads h5py

        with h5safe.open_untrusted(path, "PSF file") as f:
            for group, name in ((f, "psf"), (f.get("calibration"), "psf")):
                if group is not None and name in group:
                    arr = h5safe.checked_dataset(group, name, h5safe.MAX_SIDE ** 2 * h5safe.MAX_CHANNELS,
                                                 dtypes="uif", ndims=(2, 3))[()]
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


def resolvable_fraction(psf: np.ndarray, snr_px: float, contrast: float = 0.1) -> float:
    """Fraction of the grid's spatial frequencies at which the PSF carries a scene pattern of
    `contrast` above the RS image's noise floor.

    A sinusoid of contrast c in a scene of mean intensity I puts c I |H(f)| N/2 into the DFT
    bin f of an image of N pixels seen through the PSF (H(0) = 1), while white noise of
    standard deviation s per pixel puts s sqrt(N) into every bin. With snr_px = (the RS image's
    mean) / s, the pattern clears the noise where c |H(f)| snr_px sqrt(N) / 2 >= 1. Unlike a
    threshold relative to DC, this does not fall as the grid grows: a finer grid has more,
    weaker frequencies, and also more pixels to measure each one with.
    """
    mono = np.asarray(psf, dtype=np.float64).reshape(-1, *psf.shape[-2:]).mean(axis=0)
    dc = mono.sum()
    if not (np.isfinite(dc) and dc > 0 and np.isfinite(snr_px) and snr_px > 0 and contrast > 0):
        return 0.0
    transfer = np.abs(np.fft.rfft2(mono)) / dc
    return float((contrast * transfer * snr_px * np.sqrt(mono.size) / 2 >= 1).mean())


def figure_line(fraction: float, snr_px: float, contrast: float = 0.1) -> str:
    """The PSF figure as one report line."""
    return (f"PSF figure: {100 * fraction:.1f} % of the grid's frequencies carry a {100 * contrast:g} % "
            f"contrast pattern above the RS noise (RS SNR {snr_px:.0f} per pixel)")


def snr_of_mean_signal(mean_electrons: float, read_noise_e: float) -> float:
    """Per-pixel signal-to-noise of a mean signal in electrons under shot and read noise."""
    mean_electrons = max(float(mean_electrons), 0.0)
    noise = np.sqrt(mean_electrons + read_noise_e ** 2)
    return float(mean_electrons / noise) if noise > 0 else 0.0


# --------------------------------------------------------------------------- lenslet diffuser


def lenslet_spots(sensor_shape: tuple[int, int], lenslets: int = 64, spot_fwhm_px: float = 4.0,
                  coverage: float = 0.85, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Focal-spot centres (n, 2) as (row, col) in sensor pixels (pixel i spans [i, i + 1)) and their
    energies (n,) summing to 1.

    Unifocal lenslets at random places on the diffuser focus a point source to one spot each;
    the spots fall uniformly at random (no periodicity) in the central `coverage` fraction of
    each sensor side, at least two spot widths apart (two lenslets' foci do not merge). Each
    spot's energy is proportional to its lenslet's area, which varies from dent to dent.
    """
    h, w = sensor_shape
    if lenslets < 1 or not 0 < coverage <= 1 or not spot_fwhm_px > 0:
        raise ValueError("lenslets must be >= 1, coverage in (0, 1], spot_fwhm_px > 0")
    rng = np.random.default_rng([seed, 28])
    margin = 2.5 * spot_fwhm_px  # keeps every spot's light on the sensor
    lo = np.array([max(margin, h * (1 - coverage) / 2), max(margin, w * (1 - coverage) / 2)])
    hi = np.array([h, w]) - lo
    if np.any(hi <= lo):
        raise ValueError(f"a {h}x{w} sensor is too small for {spot_fwhm_px:g} px spots")
    min_sep = 2 * spot_fwhm_px
    centres: list[np.ndarray] = []
    for _ in range(200 * lenslets):
        p = lo + rng.random(2) * (hi - lo)
        if all(np.hypot(*(p - q)) >= min_sep for q in centres):
            centres.append(p)
            if len(centres) == lenslets:
                break
    else:
        raise ValueError(f"cannot place {lenslets} spots {min_sep:g} px apart on a {h}x{w} sensor "
                         f"(coverage {coverage:g})")
    energy = rng.uniform(0.5, 1.5, lenslets)
    return np.array(centres), energy / energy.sum()


def bin_sum(img: np.ndarray, binning: int) -> np.ndarray:
    """Sum (..., H, W) over binning x binning blocks, as a camera's binning does (energy kept)."""
    h, w = img.shape[-2:]
    if h % binning or w % binning:
        raise ValueError(f"a {h}x{w} image does not bin by {binning}")
    return img.reshape(*img.shape[:-2], h // binning, binning, w // binning, binning).sum(axis=(-3, -1))


def render_spots(sensor_shape: tuple[int, int], centres: np.ndarray, energy: np.ndarray,
                 spot_fwhm_px: float) -> np.ndarray:
    """(H, W) float64: Gaussian spots integrated over each pixel (each spot's pixels sum to its energy)."""
    from scipy.special import erf  # heavy: scipy

    img = np.zeros(sensor_shape)
    sigma = spot_fwhm_px / (2 * np.sqrt(2 * np.log(2)))
    r = int(np.ceil(5 * sigma)) + 1
    for (cy, cx), e in zip(centres, energy):
        y0, x0 = max(int(cy) - r, 0), max(int(cx) - r, 0)
        y1, x1 = min(int(cy) + r + 1, sensor_shape[0]), min(int(cx) + r + 1, sensor_shape[1])
        ey = np.diff(erf((np.arange(y0, y1 + 1) - cy) / (np.sqrt(2) * sigma))) / 2
        ex = np.diff(erf((np.arange(x0, x1 + 1) - cx) / (np.sqrt(2) * sigma))) / 2
        img[y0:y1, x0:x1] += e * np.outer(ey, ex)
    return img


def lenslet_psf(grid_shape: tuple[int, int], binning: int = 8, lenslets: int = 64,
                spot_fwhm_px: float = 4.0, coverage: float = 0.85, seed: int = 0) -> np.ndarray:
    """(1, *grid_shape) PSF of a random unifocal-lenslet diffuser (the RnGCam paper's kind).

    Rendered on a sensor of grid_shape x binning pixels (spot width `spot_fwhm_px` in those
    pixels), then binned like a measured PSF and normalised to sum 1.
    """
    sensor = (grid_shape[0] * binning, grid_shape[1] * binning)
    centres, energy = lenslet_spots(sensor, lenslets, spot_fwhm_px, coverage, seed)
    return normalise(bin_sum(render_spots(sensor, centres, energy, spot_fwhm_px), binning)[None])


def binning_matrix(n: int, factor: int) -> np.ndarray:
    """(m, n) weights along one axis that bin a PSF of n sensor pixels to the grid (`factor` sensor
    pixels a grid pixel) exactly for a scene constant over each grid pixel: that scene, blurred at
    the sensor's resolution and binned like the frames, is the grid image blurred by the binned PSF.
    Sensor pixel i reaches grid pixel j with the triangle (factor - |d|) / factor,
    d = i - factor (j - m // 2) - n // 2 (pixel n // 2 is a point's own sensor pixel, m // 2 its own
    grid pixel). m is the smallest size that holds every weight with that centre: the triangle
    reaches one grid pixel past n / factor, where a plain binned PSF loses its outer ring."""
    f, c = int(factor), n // 2
    if f < 1 or f != factor:
        raise ValueError(f"binning must be a positive integer, got {factor}")
    lo = (c + f - 1) // f  # grid pixels the weights reach below the centre
    hi = (n - 1 - c + f - 1) // f  # and above it
    m = lo + hi + 1
    while m // 2 < lo or m - 1 - m // 2 < hi:
        m += 1
    d = np.arange(n)[None, :] - f * (np.arange(m)[:, None] - m // 2) - c
    return np.clip(f - np.abs(d), 0, None) / f


def bin_psf(raw: np.ndarray, factor: int) -> np.ndarray:
    """(C, Hp, Wp) PSF at the sensor's resolution -> (C, h, w) on a grid of `factor` x `factor`
    sensor pixels, summing to 1 per channel, exact for a scene constant over each grid pixel
    (binning_matrix; h is Hp / factor + 1 for even Hp / factor). Factor 1 keeps the PSF as it is."""
    raw = as_chw(np.asarray(raw, np.float64))
    my, mx = binning_matrix(raw.shape[-2], factor), binning_matrix(raw.shape[-1], factor)
    return normalise(my @ raw @ mx.T)


def magnify_matrix(n: int, factor: float, centre: float | None = None) -> np.ndarray:
    """(n, n) area-resampling matrix along one axis: pixel k (spanning [k, k + 1)) magnified by
    `factor` about `centre` (default the centre of pixel n // 2, a PSF's own point) spans
    [c + (k - c) f, c + (k + 1 - c) f); output pixel i receives the share of it that falls in
    [i, i + 1). Columns sum to 1 where nothing falls off the edge (energy kept)."""
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"magnification must be positive, got {factor}")
    c = n // 2 + 0.5 if centre is None else float(centre)
    edges = c + (np.arange(n + 1, dtype=np.float64) - c) * factor  # input pixel k spans edges[k:k + 2]
    lo = np.maximum(np.arange(n)[:, None], edges[None, :-1])
    hi = np.minimum(np.arange(n)[:, None] + 1.0, edges[None, 1:])
    return np.clip(hi - lo, 0.0, None) / factor


def even_blur(matrix: np.ndarray, variance: float) -> np.ndarray:
    """`matrix` (a resampling matrix, rows = output pixels) followed by a 3-tap blur per output
    pixel that brings each row's spread (its weights' variance, in pixels^2) up to `variance`:
    resampled versions then share one blur, whatever their sub-pixel phases (an exact copy has
    none, a magnified one mixes neighbours by their phase)."""
    n = matrix.shape[0]
    k = np.arange(matrix.shape[1]) + 0.5
    w = matrix.sum(1).clip(1e-12)
    mean = (matrix * k).sum(1) / w
    spread = (matrix * (k[None] - mean[:, None]) ** 2).sum(1) / w
    a = np.clip(variance - spread, 0.0, 2.0 / 3.0)
    blur = np.diag(1 - a) + np.diag(a[:-1] / 2, 1) + np.diag(a[1:] / 2, -1)
    return blur[:n, :n] @ matrix


def magnify(psf: np.ndarray, factor: float, blur: float | None = None) -> np.ndarray:
    """(C, H, W) PSF magnified by `factor` about its centre pixel (H // 2, W // 2), pixels treated as
    uniform squares (exact area resampling), then normalised to sum 1 per channel: the PSF of a
    scene at another distance than the calibration's point source. With `blur` (pixels^2 per
    axis), every output pixel blurred to that spread (even_blur): candidates of a search compared
    on equal terms."""
    psf = np.asarray(psf, np.float64)
    h, w = psf.shape[-2:]
    my, mx = magnify_matrix(h, factor), magnify_matrix(w, factor)
    if blur is not None:
        my, mx = even_blur(my, blur), even_blur(mx, blur)
    return normalise(my @ psf @ mx.T)  # two matrix products (a three-operand einsum loops over all four axes)
