"""Self-calibration: the GS-to-RS transform refined from the data during a fit.

Calibration leaves the GS frames misregistered against the RS image by a fraction of a pixel, a
small rotation and scale (`calibrate align`: 0.28 px median residual on the mock rig). A fit
anchored to the GS frames then reconstructs the video in the GS camera's coordinates, and the RS
image, which sees the scene in its own, cannot be fitted there.

The estimate, by registration against the RS image: for the current video V find the similarity
T (shift, rotation, scale about the grid's centre) for which the RS operator applied to V o T
reproduces the RS image best (a few L-BFGS steps on 4 numbers). If V was reconstructed in
coordinates E away from the RS camera's (V = v o E^-1 ... V o T ~ v), then E = T^-1, and the GS
prediction's warp S (the GS camera sees the video at S(p), p a GS pixel) becomes T^-1 o S. Repeated
as the fit moves V towards the RS coordinates, S converges to the true transform.

Transforms are 3x3 matrices acting on pixel coordinates (x, y) measured from the grid's centre
(pixel centres at i + 0.5 - W / 2), the convention of rngcam.sim.fidelity's truth values.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


def similarity(dx: float = 0.0, dy: float = 0.0, rotation_rad: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """3x3: p -> scale R(rotation) p + (dx, dy)."""
    c, s = math.cos(rotation_rad) * scale, math.sin(rotation_rad) * scale
    return np.array([[c, -s, dx], [s, c, dy], [0.0, 0.0, 1.0]])


def describe(matrix) -> dict:
    """The shift (px), rotation (degrees) and scale of a similarity matrix."""
    m = np.asarray(matrix, np.float64)
    return {"shift_px": [float(m[0, 2]), float(m[1, 2])],
            "rotation_deg": float(np.degrees(math.atan2(m[1, 0], m[0, 0]))),
            "scale": float(math.hypot(m[0, 0], m[1, 0]))}


def _matrix_t(params: Tensor) -> Tensor:
    """params (dx, dy, rotation, log scale) -> 3x3 (differentiable)."""
    dx, dy, rot, log_s = params
    s = torch.exp(log_s)
    c, n = torch.cos(rot) * s, torch.sin(rot) * s
    zero, one = torch.zeros_like(dx), torch.ones_like(dx)
    return torch.stack([torch.stack([c, -n, dx]), torch.stack([n, c, dy]), torch.stack([zero, zero, one])])


def sample_grid(matrix: Tensor, h: int, w: int) -> Tensor:
    """(1, H, W, 2) grid_sample coordinates (align_corners=False) of M p for every pixel p."""
    dev, dt = matrix.device, matrix.dtype
    ys = torch.arange(h, device=dev, dtype=dt) + 0.5 - h / 2
    xs = torch.arange(w, device=dev, dtype=dt) + 0.5 - w / 2
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    qx = matrix[0, 0] * xx + matrix[0, 1] * yy + matrix[0, 2]
    qy = matrix[1, 0] * xx + matrix[1, 1] * yy + matrix[1, 2]
    return torch.stack([qx * (2.0 / w), qy * (2.0 / h)], dim=-1)[None]


def warp(images: Tensor, matrix: Tensor | np.ndarray) -> Tensor:
    """images (C, N, H, W) sampled at M p (bicubic, border values outside): out(p) = in(M p)."""
    c, n, h, w = images.shape
    m = torch.as_tensor(np.asarray(matrix) if not isinstance(matrix, Tensor) else matrix,
                        dtype=images.dtype, device=images.device)
    grid = sample_grid(m, h, w).expand(n, h, w, 2)
    out = torch.nn.functional.grid_sample(images.transpose(0, 1), grid, mode="bicubic",
                                          padding_mode="border", align_corners=False)
    return out.transpose(0, 1)


def is_identity(matrix, tol: float = 1e-9) -> bool:
    return bool(np.allclose(np.asarray(matrix), np.eye(3), atol=tol))


def register_to_rs(video: Tensor, rs_forward, b_rs: Tensor, valid: Tensor | None = None,
                   iters: int = 20, frame_chunk: int = 16, free: int = 4) -> tuple[np.ndarray, float, float]:
    """The similarity T minimising ||A_R(V o T) - b_rs||^2 (see module docstring).

    video (C, K, H, W); rs_forward(v) -> (C, H, W) differentiable. Returns (T as 3x3, relative
    RS residual at the identity, at T). Frames the RS image does not see cost nothing."""
    video = video.detach()
    target = b_rs if valid is None else b_rs * valid
    norm = float(target.square().sum().clamp_min(1e-30))
    params = torch.zeros(free, dtype=torch.float64, device=video.device, requires_grad=True)

    def full() -> Tensor:
        return torch.cat([params, torch.zeros(4 - free, dtype=params.dtype, device=params.device)])

    def misfit() -> Tensor:
        m = _matrix_t(full()).to(video.dtype)
        pred = rs_forward(warp(video, m))
        miss = pred - b_rs
        if valid is not None:
            miss = miss * valid
        return miss.square().sum().double() / norm

    with torch.no_grad():
        start = float(misfit())
    opt = torch.optim.LBFGS([params], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14)

    def closure():
        opt.zero_grad()
        loss = misfit()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        end = float(misfit())
        if not (math.isfinite(end) and end < start):  # no better than the identity: keep it
            return np.eye(3), math.sqrt(start), math.sqrt(start)
        return _matrix_t(full().detach()).cpu().numpy(), math.sqrt(start), math.sqrt(end)


# ----------------------------------------------------------------------------- key rows

KEY_ROW_OVERLAP = 0.85  # an RS row bin whose exposure covers this share of a GS exposure sees that key frame


def key_rows(rs_weights: Tensor, gs_weights: Tensor, overlap: float = KEY_ROW_OVERLAP) -> list[tuple[int, np.ndarray]]:
    """(GS frame g, the RS row bins exposed over (nearly) the same window as g) for every g that has some.

    Overlap of two exposures: sum_k min(w_r[k], w_g[k]) / max(sum w_r, sum w_g)."""
    rs_w, gs_w = rs_weights.double().cpu(), gs_weights.double().cpu()
    out = []
    for g in range(gs_w.shape[0]):
        shared = torch.minimum(rs_w, gs_w[g][None]).sum(1)
        denom = torch.maximum(rs_w.sum(1), gs_w[g].sum()).clamp_min(1e-12)
        rows = torch.nonzero(shared / denom >= overlap).flatten().numpy()
        if len(rows):
            out.append((g, rows))
    return out


def register_key_rows(problem, iters: int = 30, free: int = 4) -> dict | None:
    """GS-to-RS similarity S and GS/RS gains from the RS rows exposed with a GS frame.

    Such a row sees the scene the GS frame saw (over the same window): through the PSF, it is row
    r of the GS image taken to RS coordinates (sampled at S^-1), times the gains, times its
    exposure. Fitting S^-1 (`free` of shift x, y, rotation, log scale) and the gains to those rows
    is a small least-squares problem, independent of how anything moves between key frames.
    Returns {"matrix": S (3x3), "gains": (C,), "rs_residual_before"/"after": relative, "rows": n}
    or None without such rows."""
    if problem.b_rs is None or problem.b_gs is None:
        return None
    pairs = key_rows(problem.rs_weights, problem.gs_weights)
    if not pairs:
        return None
    p = problem.to(torch.float64)
    images = p.gs_images()  # (C, G, H, W) video intensity, GS scale
    c = images.shape[0]
    conv = p.rs_op().conv
    valid = p.rs_valid_mask()
    rowsum = p.rs_weights.sum(1)  # a constant video's row r is scaled by its total weight
    sel = [(g, torch.from_numpy(rows)) for g, rows in pairs]
    targets = [p.b_rs[:, rows] * (1 if valid is None else valid[:, rows]) for _, rows in sel]
    norm = float(sum(t.square().sum() for t in targets).clamp_min(1e-30))
    gain0 = torch.ones(c, dtype=torch.float64) if p.white_balance is None else p.white_balance.double()
    params = torch.zeros(free, dtype=torch.float64, requires_grad=True)
    log_gain = torch.log(gain0.clone()).requires_grad_(True)

    def misfit() -> Tensor:
        m = _matrix_t(torch.cat([params, torch.zeros(4 - free, dtype=params.dtype)]))
        total = torch.zeros((), dtype=torch.float64)
        for (g, rows), target in zip(sel, targets, strict=True):
            img = warp(images[:, g:g + 1], m)[:, 0] * torch.exp(log_gain)[:, None, None]
            pred = conv.A(img)[:, rows] * rowsum[rows][None, :, None]
            if valid is not None:
                pred = pred * valid[:, rows]
            total = total + (pred - target).square().sum()
        return total / norm

    with torch.no_grad():
        start = float(misfit())
    opt = torch.optim.LBFGS([params, log_gain], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-15)

    def closure():
        opt.zero_grad()
        loss = misfit()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        end = float(misfit())
        if not (math.isfinite(end) and end < start):
            return {"matrix": np.eye(3), "gains": gain0.numpy(), "rs_residual_before": math.sqrt(start),
                    "rs_residual_after": math.sqrt(start), "rows": int(sum(len(r) for _, r in sel))}
        inv = _matrix_t(torch.cat([params, torch.zeros(4 - free, dtype=params.dtype)])).numpy()
        return {"matrix": np.linalg.inv(inv), "gains": torch.exp(log_gain).numpy(),
                "rs_residual_before": math.sqrt(start), "rs_residual_after": math.sqrt(end),
                "rows": int(sum(len(r) for _, r in sel))}
