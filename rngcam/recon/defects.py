"""Hot and dead pixels: fixed-pattern outliers found in the measurements themselves.

A hot pixel (dark current) reads high and a dead one reads its black level in every frame, at
the same place. On the grid each is one pixel far from its 3x3 neighbourhood's median while the
image around it is not: the RS image (seen through the diffuser) is smooth at that scale, and a
GS key-frame pixel that stands out the same way in every key frame while its neighbours do not
is the sensor, not the scene. The test: the pixel above the largest (or below the smallest) of
its 8 neighbours by THRESHOLD robust standard deviations (1.4826 MAD of x - median3x3(x) over the
image) in every frame, the same way: an edge or a line of texture always has a neighbour alike.
The test runs on the frames at the sensor's resolution, before binning: a hot pixel stands out
there by its full offset, where a bin of f x f sensor pixels dilutes it f^2 times (on the lab
family at 2x binning: 22 of 24 RS and 24 of 24 GS defects found at the sensor's resolution, against
20 and 7-22 of 24 on the binned grid). Where frames are binned, each such pixel is replaced by the
median of its 8 neighbours before binning (`fill`), so the grid pixel keeps its other f^2 - 1
measurements; unbinned, it leaves the data terms (the problem's rs_valid / gs_valid masks).
Pixels on the image's edge are tested against their 5 (corner: 3) neighbours inside the image."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter, median_filter, minimum_filter

_RING = np.ones((3, 3), bool)
_RING[1, 1] = False  # the 8 neighbours: an edge or a line of texture has some alike

THRESHOLD = 8.0  # robust standard deviations; the lab family's hot pixels sit at 15-100


def outliers(frames: np.ndarray, threshold: float = THRESHOLD) -> np.ndarray:
    """(H, W) bool: pixels that are outliers of the same sign in every frame of `frames`
    (C, F, H, W) or (C, H, W), in any channel."""
    f = np.asarray(frames)
    if f.ndim == 3:
        f = f[:, None]
    c, n, h, w = f.shape
    if h < 3 or w < 3:
        return np.zeros((h, w), bool)
    found = np.zeros((h, w), bool)
    for ch in range(c):
        pos = np.ones((h, w), bool)
        neg = np.ones((h, w), bool)
        for i in range(n):
            x = np.asarray(f[ch, i], np.float32 if f.dtype == np.float32 else np.float64)  # a frame at a time
            sigma = _robust_sigma(x)
            if not sigma > 0:
                pos[:] = neg[:] = False
                break
            # "mirror" (not "reflect", which repeats the edge pixel itself): an edge pixel's
            # neighbours are the image's own
            pos &= x - maximum_filter(x, footprint=_RING, mode="mirror") > threshold * sigma
            neg &= minimum_filter(x, footprint=_RING, mode="mirror") - x > threshold * sigma
            if not (pos.any() or neg.any()):
                break
        found |= pos | neg
    return found


SIGMA_SAMPLE = 1_000_000  # pixels the noise scale is estimated from (a sensor-sized frame needs no more)


def _robust_sigma(x: np.ndarray) -> float:
    """1.4826 MAD of x - median3x3(x), from a central crop of at most SIGMA_SAMPLE pixels."""
    h, w = x.shape
    side = int(np.sqrt(SIGMA_SAMPLE))
    y0, x0 = max(0, (h - side) // 2), max(0, (w - side) // 2)
    crop = x[y0:y0 + side, x0:x0 + side]
    d = crop - median_filter(crop, size=3, mode="mirror")
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def fill(frames: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """frames (C, ..., H, W) with the pixels `bad` (H, W) replaced by the median of their 8
    neighbours that are not bad themselves (in place; returns frames)."""
    ys, xs = np.nonzero(bad)
    if not len(ys):
        return frames
    h, w = bad.shape
    for y, x in zip(ys, xs, strict=True):
        y0, y1, x0, x1 = max(0, y - 1), min(h, y + 2), max(0, x - 1), min(w, x + 2)
        good = ~bad[y0:y1, x0:x1]
        if good.any():
            frames[..., y, x] = np.median(frames[..., y0:y1, x0:x1][..., good], axis=-1)
    return frames
