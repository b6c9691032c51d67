"""Hot and dead pixels: fixed-pattern outliers found in the measurements themselves.

A hot pixel (dark current) reads high and a dead one reads its black level in every frame, at
the same place. On the grid each is one pixel far from its 3x3 neighbourhood's median while the
image around it is not: the RS image (seen through the diffuser) is smooth at that scale, and a
GS key-frame pixel that stands out the same way in every key frame while its neighbours do not
is the sensor, not the scene. The test: the pixel above the largest (or below the smallest) of
its 8 neighbours by THRESHOLD robust standard deviations (1.4826 MAD of x - median3x3(x) over the
image) in every frame, the same way: an edge or a line of texture always has a neighbour alike.
Such pixels leave the data terms (the problems' rs_valid / gs_valid masks)."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter, median_filter, minimum_filter

THRESHOLD = 8.0  # robust standard deviations; the lab family's hot pixels sit at 15-100


def outliers(frames: np.ndarray, threshold: float = THRESHOLD) -> np.ndarray:
    """(H, W) bool: pixels that are outliers of the same sign in every frame of `frames`
    (C, F, H, W) or (C, H, W), in any channel."""
    f = np.asarray(frames, np.float64)
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
            x = f[ch, i]
            d = x - median_filter(x, size=3, mode="reflect")
            sigma = 1.4826 * np.median(np.abs(d - np.median(d)))
            if not sigma > 0:
                pos[:] = neg[:] = False
                break
            ring = np.ones((3, 3), bool)
            ring[1, 1] = False  # the 8 neighbours: an edge or a line of texture has some alike
            pos &= x - maximum_filter(x, footprint=ring, mode="reflect") > threshold * sigma
            neg &= minimum_filter(x, footprint=ring, mode="reflect") - x > threshold * sigma
        found |= pos | neg
    return found
