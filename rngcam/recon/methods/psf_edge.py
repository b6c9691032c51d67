"""A PSF measured too large: its lost edge fitted from a video that explains the rest of the data.

A diffuser's PSF scales with the object's distance. Calibrated with a point source nearer than
the scene, it is magnified, and its outer ring fell off the sensor: shrunk to the scene's scale
it lacks that ring (13 % of the mock caustic's energy for 5 %), and neither it nor the PSF as
handed explains the RS image (bench/realistic.md). The RS measurement is linear in the PSF, so
given a video (a first fit's), the ring's pixels and a factor on the shrunk PSF are a
non-negative least-squares fit to the RS rows. The fit then runs again through that PSF
(rngcam.recon.methods.stfm.edge_refit).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rngcam.physics.operators import RollingShutter
from rngcam.recon.methods.nnls import nnls_normal
from rngcam.recon.methods.selfcal import line_search
from rngcam.recon.metrics import relative_residual

MAX_DESIGN = 4_000_000  # design-matrix entries per PSF channel: sensor rows beyond it are subsampled
MIN_EQUATIONS = 4  # RS pixels per unknown a fit needs, or the edge takes up noise (None: not fitted)


def edge_mask(shape: tuple[int, int], scale: float) -> np.ndarray:
    """(Hp, Wp) bool: the pixels a PSF shrunk by `scale` (rngcam.physics.psf.magnify) does not
    fully cover, with their neighbours: its lost edge (none for scale >= 1). A grid pixel of a PSF
    binned from the sensor (physics.psf.bin_psf) gathers sensor pixels up to one grid pixel past its
    own square, so the light the sensor lost reaches one pixel further in than the shrink shows."""
    from rngcam.physics.psf import magnify_matrix  # heavy: psf loads cv2

    if scale >= 1:
        return np.zeros(shape, bool)
    lost = []
    for n in shape:
        full = np.pad(magnify_matrix(n, scale).sum(1) * scale >= 1 - 1e-6, 1)  # share of each pixel covered
        lost.append(~(full[:-2] & full[1:-1] & full[2:]))
    return lost[0][:, None] | lost[1][None, :]


def _row_videos(video: Tensor, weights: Tensor, rows: Tensor) -> Tensor:
    """(C, R, H, W): for each sensor row r of `rows`, the video summed over time with r's weights."""
    return torch.einsum("rk,ckyx->cryx", weights[rows].to(video), video)


def _columns(row_video: Tensor, rows: Tensor, pixels: np.ndarray, offset: tuple[int, int]) -> Tensor:
    """(C, R, W, N): the RS rows `rows` a PSF of one at each of `pixels` (N, 2) would give
    (rngcam.physics.operators.PSFConvolution: sensor (i, x) sees video (i + oy - py, x + ox - px))."""
    c, r, h, w = row_video.shape
    py = torch.from_numpy(pixels[:, 0]).long()
    px = torch.from_numpy(pixels[:, 1]).long()
    ys = rows[:, None] + offset[0] - py[None]  # (R, N)
    xs = torch.arange(w)[:, None] + offset[1] - px[None]  # (W, N)
    inside = ((ys >= 0) & (ys < h))[:, None, :] & ((xs >= 0) & (xs < w))[None]  # (R, W, N)
    ri = torch.arange(r)[:, None, None]
    cols = row_video[:, ri, ys.clamp(0, h - 1)[:, None, :], xs.clamp(0, w - 1)[None]]
    return cols * inside


def fit_edge(problem, video: Tensor, scale: float, seed: int = 0) -> dict | None:
    """The PSF shrunk by `scale` with its lost edge (edge_mask) fitted to the RS rows given `video`
    (C, K, H, W, on the RS scale): per PSF channel, non-negative a * shrunk + edge, normalised.
    Returns {"psf" (a Tensor like problem.psf), "scale", "edge_pixels", "edge_energy" (per channel),
    "residual_shrunk" (the shrunk PSF with the best factor), "residual" (the fitted PSF)}, the
    residuals relative, over the rows the fit used; None without an RS image or an edge, or where
    the rows the design affords (MAX_DESIGN) give fewer than MIN_EQUATIONS pixels per unknown."""
    from rngcam.physics.psf import magnify  # heavy: psf loads cv2

    if problem.b_rs is None or not (math.isfinite(scale) and 0 < scale < 1):
        return None
    psf = problem.psf.detach().double().cpu()
    mask = edge_mask(tuple(psf.shape[-2:]), scale)
    if not mask.any():
        return None
    pixels = np.argwhere(mask)
    c, h, w = problem.b_rs.shape
    v = video.detach().double().cpu()
    b = problem.b_rs.detach().double().cpu()
    if not (bool(torch.isfinite(v).all()) and bool(torch.isfinite(b).all())):
        return None
    valid = problem.rs_valid_mask()
    valid = torch.ones_like(b) if valid is None else valid.detach().double().cpu().expand_as(b)
    n_rows = min(h, max(4, MAX_DESIGN // max(1, w * len(pixels))))
    if n_rows * w < MIN_EQUATIONS * (len(pixels) + 1):  # a large grid: the edge has too many pixels
        return None
    rows = torch.arange(h) if n_rows >= h else torch.from_numpy(
        np.sort(np.random.default_rng(seed).choice(h, n_rows, replace=False)))
    shrunk = torch.from_numpy(magnify(psf.numpy(), scale))
    weights = problem.rs_weights.detach().double().cpu()
    base = RollingShutter(shrunk, weights, w, channels=c).A(v)[:, rows] * valid[:, rows]
    cols = _columns(_row_videos(v, weights, rows), rows, pixels, (psf.shape[-2] // 2, psf.shape[-1] // 2))
    cols = cols * valid[:, rows, :, None]
    target = b[:, rows] * valid[:, rows]
    groups = [[ch] for ch in range(c)] if psf.shape[0] == c else [list(range(c))]  # channels sharing a PSF
    out = shrunk.clone()
    fitted_pred = torch.zeros_like(target)
    shrunk_pred = torch.zeros_like(target)
    energy = []
    for p_ch, chans in enumerate(groups):
        design = torch.cat([torch.cat([base[ch].reshape(-1, 1), cols[ch].reshape(-1, len(pixels))], 1)
                            for ch in chans]).numpy()
        y = torch.cat([target[ch].reshape(-1) for ch in chans]).numpy()
        try:
            x = nnls_normal(design, y)
        except RuntimeError:  # no convergence
            return None
        full = x[0] * shrunk[p_ch].numpy()
        full[mask] += x[1:]
        total = full.sum()
        if not (math.isfinite(total) and total > 0):
            return None
        out[p_ch] = torch.from_numpy(full / total)
        energy.append(float(x[1:].sum() / total))
        fitted_pred[chans] = torch.from_numpy(design @ x).reshape(len(chans), len(rows), w)
        a = float((base[chans] * target[chans]).sum() / base[chans].square().sum().clamp_min(1e-30))
        shrunk_pred[chans] = a * base[chans]
    return {"psf": out.to(problem.psf.dtype), "scale": float(scale), "edge_pixels": int(len(pixels)),
            "edge_energy": energy, "rows": int(len(rows)),
            "residual_shrunk": relative_residual(shrunk_pred, target),
            "residual": relative_residual(fitted_pred, target)}


EDGE_SCALES = (0.90, 0.99)  # the shrinks searched (a PSF measured up to ~10 % too large)
_COARSE, _FINE = 0.015, 0.005


def search_edge(problem, video: Tensor, scales: tuple[float, float] = EDGE_SCALES) -> dict | None:
    """fit_edge at the shrink that explains the RS rows best: a coarse search over `scales`, a finer
    one around the best and a parabola through the lowest three (the key rows alone place it short:
    sineball with its PSF 5 % large, 0.978 for 0.952; with the edge fitted, the residual is lowest
    at 0.952). fit_edge's dict with "searched" [(scale, residual), ...]; None where none fits."""
    tried: dict[float, dict | None] = {}

    def at(s: float) -> float:
        s = round(float(s), 6)
        if s not in tried:
            tried[s] = fit_edge(problem, video, s) if math.isfinite(s) else None
        return tried[s]["residual"] if tried[s] is not None else math.inf

    estimate = line_search(at, *scales, _COARSE, _FINE, _COARSE)
    if tried.get(round(estimate, 6)) is None:
        return None
    found = dict(tried[round(estimate, 6)])
    found["searched"] = sorted((s, r["residual"]) for s, r in tried.items() if r is not None)
    return found
