"""The key rows: the RS row bins exposed over (nearly) the same window as a GS frame, which see the
scene that frame saw (rngcam.recon.methods.selfcal fits the calibration to them)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

KEY_ROW_OVERLAP = 0.85  # an RS row bin whose exposure covers this share of a GS exposure sees that key frame


def key_rows(rs_weights: Tensor, gs_weights: Tensor, overlap: float = KEY_ROW_OVERLAP) -> list[tuple[int, np.ndarray]]:
    """(GS frame g, the RS row bins exposed over (nearly) the same window as g) for every g that has some.

    Overlap of two exposures: sum_k min(w_r[k], w_g[k]) / max(sum w_r, sum w_g)."""
    rs_w, gs_w = rs_weights.double().cpu(), gs_weights.double().cpu()
    out = []
    for g in range(gs_w.shape[0]):
        shared = torch.minimum(rs_w, gs_w[g][None]).sum(1)
        denom = torch.maximum(rs_w.sum(1), gs_w[g].sum()).clamp_min(1e-12)
        rows = torch.nonzero(shared / denom >= overlap).flatten().cpu().numpy()
        if len(rows):
            out.append((g, rows))
    return out


def _filled(images: Tensor, valid: Tensor | None) -> Tensor:
    """Invalid pixels (hot, dead, saturated) replaced by their 3x3 neighbourhood's median: through
    the PSF one hot pixel reaches the whole row."""
    if valid is None or bool(valid.all()):
        return images
    c, g, h, w = images.shape
    padded = torch.nn.functional.pad(images.reshape(c * g, 1, h, w), (1, 1, 1, 1), mode="replicate")
    med = padded.unfold(2, 3, 1).unfold(3, 3, 1).reshape(c * g, 1, h, w, 9).median(-1).values.reshape(c, g, h, w)
    return torch.where(valid.expand_as(images), images, med)


def key_row_data(problem):
    """What a fit on the key rows needs, in float64: (problem, GS images (C, G, H, W) with their
    invalid pixels filled, the RS valid mask, each row's total weight, [(GS frame, its rows)], each
    pair's measured rows); None without both cameras or without key rows."""
    if problem.b_rs is None or problem.b_gs is None:
        return None
    pairs = key_rows(problem.rs_weights, problem.gs_weights)
    if not pairs:
        return None
    p = problem.to(torch.float64)
    images = _filled(p.gs_images(), p.gs_valid)  # video intensity, GS scale
    valid = p.rs_valid_mask()
    rowsum = p.rs_weights.sum(1)  # a constant video's row r is scaled by its total weight
    sel = [(g, torch.from_numpy(rows)) for g, rows in pairs]
    targets = [p.b_rs[:, rows] * (1 if valid is None else valid[:, rows]) for _, rows in sel]
    return p, images, valid, rowsum, sel, targets


def key_row_uncertainty(misses, params: Tensor, log_gain: Tensor) -> dict:
    """Standard errors of a key-row fit's values (`misses(params, log_gain)`: its residuals),
    sigma^2 (J^T J)^-1 with sigma^2 from the residual (noise only: a model error between the rows and
    the key frames biases without showing here)."""
    n = len(params)
    x0 = torch.cat([params, log_gain])
    with torch.no_grad():
        r = misses(params, log_gain)
        cols = []
        for i in range(len(x0)):  # central differences: 2 evaluations per value, no per-residual backward
            e = torch.zeros_like(x0)
            e[i] = 1e-4
            hi, lo = x0 + e, x0 - e
            cols.append((misses(hi[:n], hi[n:]) - misses(lo[:n], lo[n:])) / 2e-4)
        jac = torch.stack(cols, dim=1)
    dof = max(len(r) - len(x0), 1)
    cov = torch.linalg.pinv(jac.T @ jac) * float(r.square().sum()) / dof
    std = cov.diagonal().clamp_min(0).sqrt().cpu().numpy()
    names = ["shift_x_px", "shift_y_px", "rotation_rad", "log_scale"][:n]
    out = {k: float(v) for k, v in zip(names, std[:n], strict=True)}
    out["gains_rel"] = [float(v) for v in std[n:]]
    return out
