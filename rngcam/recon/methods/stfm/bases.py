"""STFM's dynamic base: the GS-only video or warped key frames that the dynamic field corrects."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.methods import rife as rife_method  # looked up at each call: a test may replace them
from rngcam.recon.methods.baselines import BaselineInputError, interp, interp_warps
from rngcam.recon.methods.coarse_to_fine import bin_space
from rngcam.recon.methods.rife import RifeUnavailableError
from rngcam.recon.methods.stfm.settings import BASE_VIDEOS, HDV3_SUFFIX, KEY_WARPS, MIN_FLOW_SIZE_PX


class DynamicBase:
    """The GS-only start a dynamic field corrects, built for one fit: a video (`video`, without GS gains;
    divided by `gains` on the fly where they are given), the key frames warped by interpolation flows
    (`key_images`, `key_left`, `key_flow`, `key_logit`), the key frames' cross-fade (`keys`, `weights`),
    or none (`source` None). `substitutes`: (what was preferred, what is used instead and why)."""

    def __init__(self, grid, problem, resolved, parts, given: Tensor | None = None, gains: Tensor | None = None):
        self.grid, self.device = grid, grid.device
        self.keys = self.weights = self.video = None
        self._start_offset: Tensor | None = None  # a coarse level's key warps: _fine_start_offset
        self.source = None
        self.gains = None if gains is None else gains.to(self.device, torch.float32)
        self.substitutes: list[tuple[str, str]] = []
        kind, self.model = _rife_model_of(resolved.dynamic_base)
        if not (kind != "none" and resolved.dynamic_time and parts.gs and parts.motion):
            return
        p, H, W = problem, grid.H, grid.W
        if given is not None:
            if kind not in BASE_VIDEOS:
                raise ConfigError(f"a given base video needs a video dynamic base ({', '.join(BASE_VIDEOS)}), "
                                  f"not {kind!r}")
            self.video, self.source = given.to(self.device), "given"  # no cast copy
            return
        keys = p.gs_images()  # without gains: the current Lambda multiplies the base
        # GS-only videos and flows come from the finer grid's frames where a coarse level has them
        source = keys if p.fine_gs is None else p.fine_gs
        if kind in KEY_WARPS:
            if self._build_key_warps(problem, keys, kind, source):
                return
            kind = "interp"  # too few key frames or too small for flow
        if kind in BASE_VIDEOS:
            video, self.source, why = _base_video(source, p.gs_times_s, p.frame_times_s, kind,
                                                  self.model, _network_device(self.device))
            if source is not keys:
                video = bin_space(video, H, W)
            self.video = video.to(self.device, torch.float32)
            self.model = _resolved_model(self.model) if self.source == "rife" else None
            self.source += HDV3_SUFFIX if self.model == "hdv3" else ""
            if why:
                self.substitutes.append(("RIFE base video", f"optical-flow interpolation used instead ({why})"))
            return
        self.source = "blend"
        self.keys = keys.reshape(1, -1, H, W).to(self.device, torch.float32)
        times = torch.as_tensor(grid.gs_centre_frames(), device=self.device).float()
        self.weights = grid.blend_weights(times)

    @property
    def key_warps(self) -> bool:
        """Whether the base is the key frames warped by flows (which the motion field corrects)."""
        return self.source in ("keys_rife", "keys_rife_hdv3", "keys_interp")

    def _build_key_warps(self, problem, keys: Tensor, kind: str, source: Tensor) -> bool:
        """Per frame, the flows to its two key frames and their blend weights, from RIFE's midpoint
        flows ("keys_rife"; "keys" when RIFE is installed) or DIS optical-flow interpolation
        ("keys_interp"), that the motion and dynamic fields correct; computed on the key frames
        `source` (a finer grid's: binned to this one) and applied to `keys`. False where no flow can
        be computed (fewer than two key frames, images under MIN_FLOW_SIZE_PX)."""
        if min(source.shape[-2:]) < MIN_FLOW_SIZE_PX:  # as _base_video: no flow of either kind that small
            return False
        args = (source.detach().float().cpu().numpy(), problem.gs_times_s, problem.frame_times_s)
        warps = None
        if kind != "keys_interp" and keys.shape[0] in (1, 3):
            try:
                with torch.random.fork_rng(devices=[]):  # building the network draws random numbers
                    warps, name = rife_method.rife_warps(*args, model=self.model,
                                             device=_network_device(self.device)), "keys_rife"
            except (RifeUnavailableError, BaselineInputError) as exc:
                if kind == "keys_rife":
                    raise
                self.substitutes.append(("RIFE flows", f"DIS optical flow used instead ({_first_line(exc)})"))
        try:
            if warps is None:
                warps, name = interp_warps(*args), "keys_interp"
        except BaselineInputError:
            return False
        self.model = _resolved_model(self.model) if name == "keys_rife" else None
        name += HDV3_SUFFIX if self.model == "hdv3" else ""
        order = np.argsort(problem.gs_times_s, kind="stable")  # the warps' keys are sorted by time
        self.key_images = keys[:, order].permute(1, 0, 2, 3).to(self.device, torch.float32).contiguous()  # (G, C, H, W)
        self.key_left = torch.from_numpy(warps.left).to(self.device)
        flows = torch.from_numpy(np.concatenate([warps.flow0, warps.flow1], axis=-1))
        h, w = source.shape[-2:]
        px = torch.tensor([(w - 1) / 2, (h - 1) / 2]).clamp_min(0.5).repeat(2)  # the source grid's pixels
        flows, w0 = flows / px, torch.from_numpy(warps.weight0)  # coordinate units: the same on every grid
        fine_flows, fine_w0 = flows, w0
        if source is not keys:
            flows = bin_space(flows.permute(0, 3, 1, 2), self.grid.H, self.grid.W).permute(0, 2, 3, 1)
            w0 = bin_space(w0, self.grid.H, self.grid.W)
        self.key_flow = flows.to(self.device, torch.float32).contiguous()  # (K, H, W, 4)
        self.key_logit = _logit(w0.to(self.device, torch.float32))
        if source is not keys:  # the start warped where the flows were computed, then binned (keys_at)
            self._start_offset = _fine_start_offset(self, source[:, order], fine_flows, fine_w0)
        self.source = name
        return True

    def keys_at(self, u: Tensor, blend_logit: Tensor, idx: Tensor) -> Tensor:
        """Base "keys": the two key frames around each frame idx warped by the interpolation's
        flows plus u (n, H, W, 4) and blended with its weights plus blend_logit (n, H, W)."""
        left = self.key_left.index_select(0, idx)
        flow = self.key_flow.index_select(0, idx) + u
        logit = self.key_logit.index_select(0, idx) + blend_logit
        warped = _warp_pair(self.key_images, left, flow, logit, self.grid.xs, self.grid.ys)
        if self._start_offset is not None:
            warped = warped + self._start_offset.index_select(0, idx)
        return warped.permute(1, 0, 2, 3)

    def at(self, x: Tensor, y: Tensor, idx: Tensor) -> Tensor:
        """The base video (C, n, H, W) of frames idx sampled at the points (x, y) (n, H, W)."""
        n, C, H, W = len(idx), self.grid.C, self.grid.H, self.grid.W
        if self.video is not None:
            grid = torch.stack([x, y], dim=-1)  # (n, H, W, 2)
            frames = self.video.index_select(1, idx).permute(1, 0, 2, 3).to(grid.dtype)  # (n, C, H, W)
            out = F.grid_sample(frames, grid, mode="bilinear", padding_mode="border", align_corners=True)
            out = out.permute(1, 0, 2, 3)
            return out if self.gains is None else out / self.gains[:, None, None, None]
        grid = torch.stack([x, y], dim=-1).reshape(1, n * H, W, 2)
        keys = F.grid_sample(self.keys, grid, mode="bilinear", padding_mode="border",
                             align_corners=True).view(C, -1, n, H, W)
        return torch.einsum("cgnhw,ng->cnhw", keys, self.weights[idx])


def _fine_start_offset(base: DynamicBase, images: Tensor, flows: Tensor, weight0: Tensor, chunk: int = 16) -> Tensor:
    """(K, C, H, W): a coarse level's key-frame warps at the flows it starts from, made on the finer grid the
    flows were computed on (`images` (C, G, h, w) sorted by time, `flows` and `weight0` there) and binned,
    less the same warps made on the coarse grid. Warped on the coarse grid, bilinear sampling blurred the
    binned key frames' detail at every sub-pixel shift (a pan: 6 dB under the fine warps binned;
    bench/untuned.md, 2026-12-08, second round); what the fit changes (flow, blend) is still warped on the
    coarse grid, so with this added a step costs the same and starts at the fine warp exactly."""
    device, grid = base.device, base.grid
    h, w = images.shape[-2:]
    images = images.permute(1, 0, 2, 3).to(device, torch.float32).contiguous()  # (G, C, h, w)
    xs, ys = (torch.linspace(-1.0, 1.0, n, device=device) for n in (w, h))
    k = flows.shape[0]
    offset = torch.empty(k, images.shape[1], grid.H, grid.W, device=device)
    with torch.no_grad():
        for i in range(0, k, chunk):
            idx = torch.arange(i, min(k, i + chunk), device=device)
            left = base.key_left.index_select(0, idx)
            fine = _warp_pair(images, left, flows[i:i + chunk].to(device, torch.float32),
                              _logit(weight0[i:i + chunk].to(device, torch.float32)), xs, ys)
            coarse = _warp_pair(base.key_images, left, base.key_flow.index_select(0, idx),
                                base.key_logit.index_select(0, idx), grid.xs, grid.ys)
            offset[i:i + chunk] = bin_space(fine, grid.H, grid.W) - coarse
    return offset


def _warp_pair(images: Tensor, left: Tensor, flow: Tensor, logit: Tensor, xs: Tensor, ys: Tensor) -> Tensor:
    """(n, C, H, W): per frame, key frames `left` and `left + 1` of `images` (G, C, H, W) warped by the
    flows' halves (n, H, W, 4) on the axes xs, ys, blended by sigmoid(logit) (n, H, W)."""
    gx, gy = xs.view(1, 1, -1), ys.view(1, -1, 1)

    def warped(keys, f):
        grid = torch.stack([gx + f[..., 0], gy + f[..., 1]], dim=-1)
        return F.grid_sample(keys, grid, mode="bilinear", padding_mode="border", align_corners=True)

    w0 = warped(images.index_select(0, left), flow[..., :2])
    w1 = warped(images.index_select(0, left + 1), flow[..., 2:])
    m = torch.sigmoid(logit)[:, None]
    return m * w0 + (1 - m) * w1


def _logit(weight: Tensor) -> Tensor:
    weight = weight.clamp(1e-6, 1 - 1e-6)
    return torch.log(weight) - torch.log1p(-weight)


def _rife_model_of(kind: str) -> tuple[str, str | None]:
    """A dynamic base without its RIFE-model suffix, and that model ("hdv3"; None: the default)."""
    if kind.endswith(HDV3_SUFFIX):
        return kind[:-len(HDV3_SUFFIX)], "hdv3"
    return kind, None


def _resolved_model(model: str | None) -> str:
    return rife_method.resolve_model(model)[0]


def _first_line(exc: Exception) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _network_device(device: torch.device) -> str:
    """Where RIFE's network runs for a fit on `device`: that GPU (its flows are much of a large grid's
    set-up on a CPU), else the CPU."""
    return str(device) if device.type == "cuda" else "cpu"


def _base_video(keys: Tensor, gs_times_s, frame_times_s, kind: str, model: str | None = None,
                device: str = "cpu") -> tuple[Tensor, str, str]:
    """The GS-only video (C, K, H, W) a dynamic field corrects, which baseline made it, and why
    RIFE was not used where it was preferred ("" otherwise). `model`: the RIFE model (None: the default);
    `device`: where RIFE's network runs."""
    frames = keys.detach().float().cpu().numpy()
    if kind in ("video", "rife") and frames.shape[0] in (1, 3) and min(frames.shape[-2:]) >= MIN_FLOW_SIZE_PX:
        try:
            with torch.random.fork_rng(devices=[]):  # building the network draws random numbers
                video = rife_method.rife(frames, gs_times_s, frame_times_s, model=model, device=device)
                return torch.from_numpy(video), "rife", ""
        except RifeUnavailableError as exc:
            if kind == "rife":
                raise
            why = _first_line(exc)
    else:
        why = ""
    return torch.from_numpy(np.asarray(interp(frames, gs_times_s, frame_times_s), np.float32)), "interp", why


