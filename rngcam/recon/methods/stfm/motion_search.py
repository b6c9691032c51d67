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
pass over frames then picks one shift per frame (costs normalised by their spread), charging a
small L1 penalty on each change of shift and a larger one on the change of that change:
between key frames the RS rows often cannot tell a smooth path from a detour of 20-30 px
(sineball), and an object's velocity changes little from frame to frame. Cost: one RS forward per
candidate shift, in chunks. What it tries and charges are the fit stage's numbers
(stage_configs.MotionSearchConfig: `--set fit.search_turn=...`).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from rngcam.recon.methods.stfm.stage_configs import MotionSearchConfig
from rngcam.recon.methods.stfm.subframes import subframes_averaged

SEARCH_CHUNK = 64  # candidate shifts through the RS operator at once (memory: n frames of the grid at a time)
# At most this many grid steps a frame, per axis, whatever the speed: the Viterbi pass keeps
# K x S^2 x (2 x 5 + 1)^2 bytes of back-pointers (12 MB at 64 px; bench/realistic.md, "the motion search
# charges turns")
SEARCH_SPEED_STEPS = 5
TURN_SIDE = 64  # the image side at which `search_turn` is the penalty per px/frame (it scales with the side)
MASK_EPS = 1e-6  # keeps the object mask finite on a black background
WEIGHT_EPS = 1e-12  # an RS row no frame's exposure reaches is charged nothing (not divided by 0)
GAIN_EPS = 1e-30  # a candidate that predicts no light in a row: its best gain is 0, its misfit the row's
INT8_STATES = 128  # back-pointers over (V, V) fit in int8 below this many states, else int16


def object_mask(layer: Tensor, background: Tensor, change: float = MotionSearchConfig.layer_change) -> Tensor:
    """(H, W): 1 where `layer` (C, H, W) differs from `background` by `change` of the background's mean."""
    diff = (layer - background).abs().mean(0)
    return (diff / (change * float(background.mean()) + MASK_EPS)).clamp(0, 1)


def key_frame_layer(keys: Tensor, index: int, change: float = MotionSearchConfig.layer_change
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """The key frames' median (C, H, W), key frame `index` as the dynamic layer (C, H, W), and
    that layer's object mask (H, W): 1 where it differs from the median by `change` of its mean."""
    background = keys.median(dim=1).values
    layer = keys[:, index]
    return background, layer, object_mask(layer, background, change)


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


def candidate_shifts(h: int, w: int, device, config: MotionSearchConfig | None = None) -> tuple[Tensor, int, int]:
    """(n, 2) candidate shifts on a square grid, and the grid's size per axis and step in px."""
    config = config or MotionSearchConfig()
    reach = config.search_reach * max(h, w)
    step = max(1, int(np.ceil(2 * reach / config.search_points)))
    r = int(reach // step)
    axis = torch.arange(-r, r + 1, device=device, dtype=torch.float32) * step
    dy, dx = torch.meshgrid(axis, axis, indexing="ij")
    return torch.stack([dx.flatten(), dy.flatten()], dim=1), 2 * r + 1, step


@torch.no_grad()
def translation_track(stfm, background: Tensor, layer: Tensor, obj: Tensor, row_gains: bool = False) -> Tensor:
    """(K, 2) shift in pixels (dx, dy) of the layer in every frame of `stfm`'s problem. With
    `row_gains`, each RS row and channel is scored after its least-squares gain (>= 0): by the shape of
    its light, not by how much of it the PSF predicts (rngcam.recon.methods.stfm.row_gain_refit).
    It reads the self-check's held-out RS rows too (stfm.floor; not a split handed to the run, which a sweep
    scores): without them a fit through an accurate PSF lost sineball's ball (bench/realistic.md, "the
    held-out rows")."""
    p, dev = stfm.problem, stfm.device
    k = stfm.K
    config: MotionSearchConfig = stfm.fit_config  # the fit stage's (its MotionSearchConfig part)
    shifts, side, step = candidate_shifts(stfm.H, stfm.W, dev, config)
    n = len(shifts)
    # On subframes the pass runs over the output's frames (each charged its subframes' mean misfit), so that
    # its velocities, turn penalty and speed limit are per output frame, as without; the track is then
    # drawn through the subframes' instants.
    sub = p.subframes
    cost = torch.zeros(k // sub, n, device=dev)
    if stfm.parts.rs:
        rows = torch.arange(stfm.H, device=dev) if stfm.state.rows_held_for_check else stfm.grid.rs_rows_fit.to(dev)
        w = stfm.grid.w_rs.index_select(0, rows)  # (R, K)
        s_r = w.sum(1).clamp_min(WEIGHT_EPS)
        valid = None if stfm.grid.rs_valid is None else stfm.grid.rs_valid.index_select(1, rows)
        target = p.b_rs.index_select(1, rows) * (1 if valid is None else valid)
        target_sq = target.square().sum(-1)[:, None] if row_gains else None  # (C, 1, R)
        rs_cost = torch.zeros(len(rows), n, device=dev)
        for i in range(0, n, SEARCH_CHUNK):
            frames = shifted_frames(background, layer, obj, shifts[i:i + SEARCH_CHUNK])
            # The frame held over a row's whole exposure: the row sees s_r times its convolution.
            conv = stfm.grid.rs_op.conv.A(frames.permute(1, 0, 2, 3)).index_select(2, rows)  # (C, n, R, W)
            pred = conv * s_r[None, None, :, None] * (1 if valid is None else valid[:, None])
            if row_gains:  # ||b - a pred||^2 at the best a >= 0
                dot = (pred * target[:, None]).sum(-1).clamp_min(0)
                miss_sq = target_sq - dot.square() / pred.square().sum(-1).clamp_min(GAIN_EPS)
            else:
                miss_sq = (pred - target[:, None]).square().sum(-1)
            rs_cost[:, i:i + SEARCH_CHUNK] = miss_sq.sum(0).t()
        cost += _normalised(subframes_averaged((w / s_r[:, None]).t() @ rs_cost, sub, dim=0))  # scale-free
    if stfm.parts.gs:
        keys = p.gs_images(gains=True).float().to(dev)  # (C, G, H, W)
        g_cost = torch.zeros(keys.shape[1], n, device=dev)
        for i in range(0, n, SEARCH_CHUNK):
            frames = shifted_frames(background, layer, obj, shifts[i:i + SEARCH_CHUNK])  # (n, C, H, W)
            miss = frames[None] - keys.permute(1, 0, 2, 3)[:, None]
            if stfm.grid.mask is not None:
                miss = miss * stfm.grid.mask
            g_cost[:, i:i + SEARCH_CHUNK] = miss.square().sum((2, 3, 4))
        # Charged to the exposure's centre only: charged to every frame it touches (as the RS rows'
        # misfits are) it held the layer still there, 5-10 px off (bench/stfm_motion.md).
        centres = (np.asarray(stfm.grid.gs_centre_frames(), float) + 0.5) / sub - 0.5  # in the output's frames
        cost += _normalised(centre_weights(centres, k // sub).to(dev).t() @ g_cost)
    size = max(stfm.H, stfm.W)  # the turn penalty and speed limit scale with the image: in grid steps
    turn = config.search_turn * stfm.state.search_turn_scale * step * TURN_SIDE / size  # track_refit scales it
    speed = min(int(np.ceil(config.search_speed * size / step)), SEARCH_SPEED_STEPS)
    best = _viterbi(cost.cpu().numpy().reshape(k // sub, side, side), config.search_smooth * step, turn, speed)
    return through_subframes(shifts.cpu()[torch.from_numpy(best)], sub)


def through_subframes(track: Tensor, steps: int) -> Tensor:
    """(K, 2) shifts of the output's frames -> (K * steps, 2) at their subframes' instants: on the straight
    path from each frame's shift to its neighbour's, the first and last frames' held beyond their instants."""
    if steps == 1:
        return track
    k = len(track)
    before, after = track[(torch.arange(k) - 1).clamp_min(0)], track[(torch.arange(k) + 1).clamp_max(k - 1)]
    out = []
    for j in range(steps):
        s = (j + 0.5) / steps - 0.5  # the subframe's instant, in frames from its frame's own
        out.append(track + s * (after - track) if s > 0 else track + s * (track - before))
    return torch.stack(out, dim=1).reshape(k * steps, 2)


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


def _viterbi(cost: np.ndarray, move: float, turn: float, speed: int) -> np.ndarray:
    """Flat index per frame of the shift path minimising the sum of costs (K, S, S) plus `move` times
    each frame's L1 change of shift and `turn` times the L1 change of that change (grid steps), with
    no change over `speed` steps per axis. The state is (shift, last change): a dynamic
    programme over (S, S, V, V)."""
    k, side, _ = cost.shape
    speed = max(0, min(speed, side - 1))
    steps = np.arange(-speed, speed + 1)
    v = len(steps)
    moves = move * (np.abs(steps)[:, None] + np.abs(steps)[None, :])
    total = np.repeat(np.repeat(cost[0][:, :, None, None], v, 2), v, 3)
    came = np.zeros((k, side, side, v, v), dtype=np.int8 if v * v < INT8_STATES else np.int16)  # flat over (V, V)
    for t in range(1, k):
        turned, last = _turn_envelope(total, turn)
        total = np.full_like(total, np.inf)
        for i, dy in enumerate(steps):
            for j, dx in enumerate(steps):  # reach shift q with change d from shift q - d
                dst, src = _moved(side, dy), _moved(side, dx)
                total[dst[0], src[0], i, j] = turned[dst[1], src[1], i, j]
                came[t, dst[0], src[0], i, j] = last[dst[1], src[1], i, j]
        total += cost[t][:, :, None, None] + moves[None, None]
    y, x, i, j = np.unravel_index(int(np.argmin(total)), total.shape)
    path = [(y, x)]
    for t in range(k - 1, 0, -1):
        before = came[t, y, x, i, j]
        y, x = y - steps[i], x - steps[j]
        i, j = divmod(int(before), v)
        path.append((y, x))
    path.reverse()
    return np.array([y * side + x for y, x in path])


def _moved(side: int, d: int) -> tuple[slice, slice]:
    """Slices (to, from) along one axis for indices moved by d on a grid of `side`."""
    return slice(max(d, 0), side + min(d, 0)), slice(max(-d, 0), side + min(-d, 0))


def _turn_envelope(total: np.ndarray, penalty: float) -> tuple[np.ndarray, np.ndarray]:
    """min over the last change c' of total(q, c') + penalty |c - c'|_1 for every shift q and change
    c (total: (S, S, V, V)), by two passes per change axis (a distance transform); and the flat index
    over (V, V) of the c' each minimum came from."""
    v = total.shape[2]
    out = total.copy()
    came = np.broadcast_to(np.arange(v * v).reshape(1, 1, v, v), total.shape).copy()
    for axis in (2, 3):
        out, came = np.moveaxis(out, axis, 0), np.moveaxis(came, axis, 0)
        for i, j in [(i, i - 1) for i in range(1, v)] + [(i, i + 1) for i in range(v - 2, -1, -1)]:
            better = out[j] + penalty < out[i]
            out[i] = np.where(better, out[j] + penalty, out[i])
            came[i] = np.where(better, came[j], came[i])
        out, came = np.moveaxis(out, 0, axis), np.moveaxis(came, 0, axis)
    return out, came
