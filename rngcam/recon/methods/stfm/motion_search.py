"""A global start for STFM's motion: the translation of the dynamic layer in every frame, found by
exhaustive search over shifts against the RS rows and GS frames, smoothed in time by dynamic
programming (the paper's prior: one canonical dynamic image that the motion moves).

Gradient steps on a warp only see a few pixels around where the object already is; when the
object turns round between key frames (sineball), the start from key-frame flow is tens of pixels
off and the fit stalls there. The search scores every shift d of the layer: the frame
background (1 - o(x - d)) + layer(x - d) o(x - d) (o: the layer's object mask) is put through the
RS operator, and each RS row's misfit is charged to the frames its exposure touches (in
proportion to their weights); each GS frame's misfit to the frame(s) at its exposure's centre
(a key frame is the layer averaged over its exposure: where it is on average). A Viterbi
pass over frames with an L1 penalty `smooth` on the change of shift between frames (costs
normalised by their spread) then picks one shift per frame. Cost: one RS forward per candidate
shift, in chunks.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

SEARCH_CHUNK = 64  # candidate shifts through the RS operator at once
SEARCH_REACH = 0.6  # shifts up to this fraction of the image side each way
SEARCH_SMOOTH = 1e-3  # L1 penalty per pixel of shift change between frames (normalised costs)
SEARCH_POINTS = 64  # about this many candidate positions per axis (step 1 px up to ~107 px images)


def key_frame_layer(keys: Tensor, index: int) -> tuple[Tensor, Tensor, Tensor]:
    """The key frames' median (C, H, W), key frame `index` as the dynamic layer (C, H, W), and
    that layer's object mask (H, W): 1 where it differs from the median by 10 % of its mean."""
    background = keys.median(dim=1).values
    layer = keys[:, index]
    change = (layer - background).abs().mean(0)
    return background, layer, (change / (0.1 * float(background.mean()) + 1e-6)).clamp(0, 1)


def shifted_frames(background: Tensor, layer: Tensor, obj: Tensor, shifts: Tensor) -> Tensor:
    """(n, C, H, W): the layer and its object mask moved by each shift (n, 2) px (dx, dy) over the
    background (C, H, W)."""
    c, h, w = layer.shape
    xs = torch.linspace(-1, 1, w, device=layer.device)
    ys = torch.linspace(-1, 1, h, device=layer.device)
    gx = xs[None, None, :] - shifts[:, 0, None, None] * 2 / max(w - 1, 1)
    gy = ys[None, :, None] - shifts[:, 1, None, None] * 2 / max(h - 1, 1)
    grid = torch.stack([gx.expand(-1, h, w), gy.expand(-1, h, w)], dim=-1)
    src = torch.cat([layer, obj[None]], 0)[None].expand(len(shifts), -1, -1, -1)
    warped = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    o = warped[:, c:]
    return background[None] * (1 - o) + warped[:, :c] * o


def candidate_shifts(h: int, w: int, device) -> tuple[Tensor, int, int]:
    """(n, 2) candidate shifts on a square grid, and the grid's size per axis and step in px."""
    reach = SEARCH_REACH * max(h, w)
    step = max(1, int(np.ceil(2 * reach / SEARCH_POINTS)))
    r = int(reach // step)
    axis = torch.arange(-r, r + 1, device=device, dtype=torch.float32) * step
    dy, dx = torch.meshgrid(axis, axis, indexing="ij")
    return torch.stack([dx.flatten(), dy.flatten()], dim=1), 2 * r + 1, step


@torch.no_grad()
def translation_track(stfm, background: Tensor, layer: Tensor, obj: Tensor, row_gains: bool = False) -> Tensor:
    """(K, 2) shift in pixels (dx, dy) of the layer in every frame of `stfm`'s problem. With
    `row_gains`, each RS row and channel is scored after its least-squares gain (>= 0): by the shape of
    its light, not by how much of it the PSF predicts (rngcam.recon.methods.stfm.row_gain_refit)."""
    p, dev = stfm.problem, stfm.device
    k = stfm.K
    shifts, side, step = candidate_shifts(stfm.H, stfm.W, dev)
    n = len(shifts)
    cost = torch.zeros(k, n, device=dev)
    if stfm.parts.rs:
        rows = stfm.rs_rows_fit.to(dev)
        w = stfm.w_rs.index_select(0, rows)  # (R, K)
        s_r = w.sum(1).clamp_min(1e-12)
        valid = None if stfm.rs_valid is None else stfm.rs_valid.index_select(1, rows)
        target = p.b_rs.index_select(1, rows) * (1 if valid is None else valid)
        target_sq = target.square().sum(-1)[:, None] if row_gains else None  # (C, 1, R)
        rs_cost = torch.zeros(len(rows), n, device=dev)
        for i in range(0, n, SEARCH_CHUNK):
            frames = shifted_frames(background, layer, obj, shifts[i:i + SEARCH_CHUNK])
            # The frame held over a row's whole exposure: the row sees s_r times its convolution.
            conv = stfm.rs_op.conv.A(frames.permute(1, 0, 2, 3)).index_select(2, rows)  # (C, n, R, W)
            pred = conv * s_r[None, None, :, None] * (1 if valid is None else valid[:, None])
            if row_gains:  # ||b - a pred||^2 at the best a >= 0
                dot = (pred * target[:, None]).sum(-1).clamp_min(0)
                miss_sq = target_sq - dot.square() / pred.square().sum(-1).clamp_min(1e-30)
            else:
                miss_sq = (pred - target[:, None]).square().sum(-1)
            rs_cost[:, i:i + SEARCH_CHUNK] = miss_sq.sum(0).t()
        cost += _normalised((w / s_r[:, None]).t() @ rs_cost)
    if stfm.parts.gs:
        keys = p.gs_images(gains=True).float().to(dev)  # (C, G, H, W)
        g_cost = torch.zeros(keys.shape[1], n, device=dev)
        for i in range(0, n, SEARCH_CHUNK):
            frames = shifted_frames(background, layer, obj, shifts[i:i + SEARCH_CHUNK])  # (n, C, H, W)
            miss = frames[None] - keys.permute(1, 0, 2, 3)[:, None]
            if stfm.mask is not None:
                miss = miss * stfm.mask
            g_cost[:, i:i + SEARCH_CHUNK] = miss.square().sum((2, 3, 4))
        # Charged to the exposure's centre only: charged to every frame it touches (as the RS rows'
        # misfits are) it held the layer still there, 5-10 px off (bench/stfm_motion.md).
        cost += _normalised(centre_weights(stfm._gs_centre_frames(), k).to(dev).t() @ g_cost)
    best = _viterbi(cost.cpu().numpy().reshape(k, side, side), SEARCH_SMOOTH * step)
    return shifts.cpu()[torch.from_numpy(best)]


def centre_weights(centres, k: int) -> Tensor:
    """(G, K): each GS frame's weight on the two frames around its exposure's centre of mass
    (linear in between). A key frame is the layer averaged over its exposure: it says where the
    layer is on average, i.e. at the centre for motion that is smooth over the exposure."""
    out = torch.zeros(len(centres), k)
    for g, c in enumerate(centres):
        c = min(max(float(c), 0.0), k - 1.0)
        left = min(int(np.floor(c)), k - 2) if k > 1 else 0
        a = c - left
        out[g, left] += 1 - a
        if k > 1:
            out[g, left + 1] += a
    return out


def _normalised(cost: Tensor) -> Tensor:
    """cost with each frame's minimum removed, over the spread of the costs (frames without data: 0)."""
    cost = cost - cost.amin(1, keepdim=True)
    spread = float(cost.std())
    return cost / spread if spread > 0 else cost


def _viterbi(cost: np.ndarray, penalty: float) -> np.ndarray:
    """Flat index per frame of the shift path minimising sum of costs (K, S, S) plus penalty times
    the L1 change (in grid steps) between consecutive frames."""
    k, side, _ = cost.shape
    totals = [cost[0]]
    for t in range(1, k):
        totals.append(cost[t] + _l1_envelope(totals[-1], penalty))
    yy, xx = np.mgrid[0:side, 0:side]
    at = np.unravel_index(int(np.argmin(totals[-1])), (side, side))
    path = [at]
    for t in range(k - 2, -1, -1):
        y0, x0 = path[-1]
        score = totals[t] + penalty * (np.abs(yy - y0) + np.abs(xx - x0))
        path.append(np.unravel_index(int(np.argmin(score)), (side, side)))
    path.reverse()
    return np.array([y * side + x for y, x in path])


def _l1_envelope(d: np.ndarray, penalty: float) -> np.ndarray:
    """min over d' of d(d') + penalty |d - d'|_1 on a 2-D grid (two passes per axis)."""
    out = d.copy()
    for axis in (0, 1):
        out = np.moveaxis(out, axis, 0)
        for i in range(1, out.shape[0]):
            np.minimum(out[i], out[i - 1] + penalty, out=out[i])
        for i in range(out.shape[0] - 2, -1, -1):
            np.minimum(out[i], out[i + 1] + penalty, out=out[i])
        out = np.moveaxis(out, 0, axis)
    return out
