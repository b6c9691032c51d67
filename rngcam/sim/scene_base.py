"""What every scene renderer shares: its error, the size and key-time checks, value noise and a
smooth step (rngcam.sim.scenes and rngcam.sim.motion_kinds build on it)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from rngcam.errors import RngcamError
from rngcam.physics.timing import VideoGrid


class SceneError(RngcamError):
    """A scene cannot be rendered from the given options or clip file."""


def default_key_times(grid: VideoGrid) -> np.ndarray:
    """Centres of the first, middle and last grid frames."""
    c = grid.centres_s()
    return c[[0, (len(c) - 1) // 2, len(c) - 1]]


def key_times(grid: VideoGrid, key_times_s: Sequence[float] | None) -> np.ndarray:
    """The key frames' times, sorted (default_key_times if None); SceneError unless >= 2 distinct finite."""
    keys = default_key_times(grid) if key_times_s is None else np.sort(np.asarray(key_times_s, float))
    if keys.ndim != 1 or len(keys) < 2 or not np.all(np.isfinite(keys)) or np.any(np.diff(keys) <= 0):
        raise SceneError(f"key_times_s must be >= 2 distinct finite times, got {key_times_s!r}")
    return keys


Size = int | tuple[int, int]


def check_size(size: Size) -> tuple[int, int]:
    """N (square) or (H, W) -> (H, W), each an integer >= 8."""
    hw = (size, size) if not isinstance(size, (tuple, list)) else tuple(size)
    if len(hw) != 2 or any(int(n) != n or n < 8 for n in hw):
        raise SceneError(f"scene size must be an integer >= 8 or (H, W) of such, got {size!r}")
    return int(hw[0]), int(hw[1])


def value_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: float,
                 octaves: int = 3) -> np.ndarray:
    """Fractal value noise (H, W) in [0, 1]: random lattices, cubic-upsampled, summed over octaves."""
    h, w = shape
    total = np.zeros(shape, np.float64)
    norm = 0.0
    for o in range(octaves):
        cell = max(cell_px / 2 ** o, 1.0)
        lattice = rng.random((int(np.ceil(h / cell)) + 3, int(np.ceil(w / cell)) + 3))
        big = cv2.resize(lattice, (int(lattice.shape[1] * cell), int(lattice.shape[0] * cell)),
                         interpolation=cv2.INTER_CUBIC)
        total += 0.5 ** o * big[int(cell):int(cell) + h, int(cell):int(cell) + w]
        norm += 0.5 ** o
    total /= norm
    lo, hi = total.min(), total.max()
    return (total - lo) / (hi - lo) if hi > lo else np.zeros(shape)


def smoothstep(x: np.ndarray) -> np.ndarray:
    """3x^2 - 2x^3 of x clipped to [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)
