"""Planar transforms between the two cameras' pixel grids: similarity matrices, homographies
applied to points, and the figures that describe or compare them.

Convention (the bundle's): a 3x3 matrix maps a pixel (x, y, 1) of one image to another's;
pixel centres are at integer coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """x_rs = scale * R(rotation) (x_gs - centre) + centre + shift (pixels, degrees)."""

    shift_px: tuple[float, float]
    rotation_deg: float
    scale: float


def similarity_matrix(shift_px, rotation_deg: float, scale: float, centre) -> np.ndarray:
    """3x3 similarity about `centre` (x, y): rotate and scale there, then shift."""
    t = math.radians(rotation_deg)
    a = scale * np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    c = np.asarray(centre, dtype=np.float64)
    h = np.eye(3)
    h[:2, :2] = a
    h[:2, 2] = c - a @ c + np.asarray(shift_px, dtype=np.float64)
    return h


def apply_homography(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) points (x, y) through a 3x3 homography."""
    p = np.c_[np.asarray(points, np.float64), np.ones(len(points))] @ np.asarray(h, np.float64).T
    return p[:, :2] / p[:, 2:]


def grid_points(shape: tuple[int, int], fraction: float = 0.6, n: int = 7) -> np.ndarray:
    """An n x n grid of (x, y) points over the central `fraction` of an (H, W) image."""
    h, w = shape
    xs = (w - 1) / 2 + np.linspace(-0.5, 0.5, n) * fraction * (w - 1)
    ys = (h - 1) / 2 + np.linspace(-0.5, 0.5, n) * fraction * (h - 1)
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares 3x3 similarity with dst ~ s R src + t."""
    x, y = src[:, 0], src[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    m = np.concatenate([np.stack([x, -y, one, zero], 1), np.stack([y, x, zero, one], 1)])
    (a, b, tx, ty), *_ = np.linalg.lstsq(m, np.concatenate([dst[:, 0], dst[:, 1]]), rcond=None)
    return np.array([[a, -b, tx], [b, a, ty], [0, 0, 1.0]])


def similarity_of(h: np.ndarray, shape: tuple[int, int]) -> Similarity:
    """The similarity (about the image centre) closest to `h` over the central region of an
    (H, W) image: its shift, rotation and scale."""
    pts = grid_points(shape)
    s = fit_similarity(pts, apply_homography(h, pts))
    centre = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
    scale = math.hypot(s[0, 0], s[1, 0])
    shift = s[:2, :2] @ centre + s[:2, 2] - centre
    return Similarity((float(shift[0]), float(shift[1])), math.degrees(math.atan2(s[1, 0], s[0, 0])),
                      scale)


def transform_error_px(h_est: np.ndarray, h_true: np.ndarray, shape: tuple[int, int],
                       fraction: float = 0.6) -> float:
    """Largest distance (RS pixels) between where two GS->RS transforms put points spread over
    the central `fraction` of a GS image of `shape` (H, W)."""
    pts = grid_points(shape, fraction)
    return float(np.linalg.norm(apply_homography(h_est, pts) - apply_homography(h_true, pts), axis=1).max())
