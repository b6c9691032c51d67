"""Calibration targets the mock cameras look at: a point source, a textured chart, darkness.

The chart is an analytic function of scene coordinates (RS sensor pixels), so a camera that
sees the scene through any transform samples it exactly, with no resampling error. It is a
patch of coloured Gaussian blobs on a mid-grey card inside a dark surround: the whole card
stays inside both cameras' fields of view, as it should on the bench (light from outside
the GS field would reach the RS sensor through the diffuser and bias the white balance).
"""

from __future__ import annotations

import numpy as np

CHART_FRACTION = 0.6  # side of the card / side of the field
_BLOBS = 60


def point_source(size: int, psf_peak: float, peak_fraction: float = 0.6) -> np.ndarray:
    """(3, size, size): one bright pixel at (size // 2, size // 2).

    Its brightness puts the RS image's peak at `peak_fraction` of full scale (the RS image of
    the point is the PSF times the brightness); `psf_peak` is the PSF's largest value.
    """
    img = np.zeros((3, size, size))
    img[:, size // 2, size // 2] = peak_fraction / psf_peak
    return img


def chart(x: np.ndarray, y: np.ndarray, size: int, seed: int = 0) -> np.ndarray:
    """(3, *x.shape) linear intensity of the chart at scene points (x, y), in pixels of a
    size x size field (pixel centres at integers). Deterministic for a seed; its largest value
    on the field's pixel grid is 1."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    peak = _chart(xx, yy, size, seed).max()
    return _chart(x, y, size, seed) / peak


def _chart(x: np.ndarray, y: np.ndarray, size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 7177])
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    c = (size - 1) / 2
    half = CHART_FRACTION * size / 2
    edge = max(size / 32, 0.5)  # a soft card edge: sharper ones alias on the pixel grid
    inside = (_soft_step((half - np.abs(x - c)) / edge) * _soft_step((half - np.abs(y - c)) / edge))
    out = np.empty((3, *x.shape))
    out[:] = 0.25
    centres = rng.uniform(c - half, c + half, size=(_BLOBS, 2))
    sigmas = rng.uniform(0.025, 0.07, size=_BLOBS) * size
    colours = rng.uniform(0.0, 0.7, size=(_BLOBS, 3))
    signs = rng.choice([-0.35, 1.0], size=_BLOBS)
    for (bx, by), s, col, sign in zip(centres, sigmas, colours, signs, strict=True):
        g = np.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * s * s))
        out += sign * col[:, None, None].reshape(3, *([1] * x.ndim)) * g
    return np.clip(out, 0.02, None) * inside


def chart_image(size: int, homography: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """(3, size, size) chart as seen by a camera whose pixel p looks at scene point H p
    (H = homography, camera pixel -> scene/RS pixel; identity when None)."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    if homography is not None:
        h = np.asarray(homography, dtype=np.float64)
        w = h[2, 0] * xx + h[2, 1] * yy + h[2, 2]
        xx, yy = ((h[0, 0] * xx + h[0, 1] * yy + h[0, 2]) / w,
                  (h[1, 0] * xx + h[1, 1] * yy + h[1, 2]) / w)
    return chart(xx, yy, size, seed)


def _soft_step(t: np.ndarray) -> np.ndarray:
    """0 for t <= -0.5, 1 for t >= 0.5, smooth in between."""
    u = np.clip(t + 0.5, 0.0, 1.0)
    return u * u * (3 - 2 * u)
