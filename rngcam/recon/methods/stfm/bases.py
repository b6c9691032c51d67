"""STFM's dynamic bases: the GS-only video or warped key frames that the dynamic field corrects."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.methods.coarse_to_fine import bin_space
from rngcam.recon.methods.stfm.settings import BASE_VIDEOS, HDV3_SUFFIX, KEY_WARPS, MIN_FLOW_SIZE_PX


class BaseVideos:
    """Part of STFM: builds the dynamic base of a fit (see the package docstring)."""

    def _build_base(self) -> None:
        """Key frames (without gains) and cross-fade weights for a dynamic field on a base."""
        self.base_keys = self.base_weights = self.base_video = None
        self.base_source = None
        self.substitutes: list[tuple[str, str]] = []  # (what was preferred, what is used instead and why)
        kind, self.base_model = _rife_model_of(self.resolved.dynamic_base)
        if not (kind != "none" and self.resolved.dynamic_time and self.parts.gs and self.parts.motion):
            return
        p = self.problem
        if self._given_base is not None:
            if kind not in BASE_VIDEOS:
                raise ConfigError(f"a given base video needs a video dynamic base ({', '.join(BASE_VIDEOS)}), "
                                  f"not {kind!r}")
            self.base_video, self.base_source = self._given_base.to(self.device), "given"  # no cast copy
            return
        keys = p.gs_images()  # without gains: the current Lambda multiplies the base
        # GS-only videos and flows come from the finer grid's frames where a coarse level has them
        source = keys if p.fine_gs is None else p.fine_gs
        if kind in KEY_WARPS:
            if self._build_key_warps(keys, kind, source):
                return
            kind = "interp"  # too few key frames or too small for flow
        if kind in BASE_VIDEOS:
            video, self.base_source, why = _base_video(source, p.gs_times_s, p.frame_times_s, kind,
                                                       self.base_model, _network_device(self.device))
            if source is not keys:
                video = bin_space(video, self.H, self.W)
            self.base_video = video.to(self.device, torch.float32)
            self.base_model = _resolved_model(self.base_model) if self.base_source == "rife" else None
            self.base_source += HDV3_SUFFIX if self.base_model == "hdv3" else ""
            if why:
                self.substitutes.append(("RIFE base video", f"optical-flow interpolation used instead ({why})"))
            return
        self.base_source = "blend"
        self.base_keys = keys.reshape(1, -1, self.H, self.W).to(self.device, torch.float32)
        times = torch.as_tensor(self._gs_centre_frames(), device=self.device).float()
        self.base_weights = self._blend_weights(times)

    def _build_key_warps(self, keys: Tensor, kind: str, source: Tensor) -> bool:
        """Per frame, the flows to its two key frames and their blend weights, from RIFE's midpoint
        flows ("keys_rife"; "keys" when RIFE is installed) or DIS optical-flow interpolation
        ("keys_interp"), that the motion and dynamic fields correct; computed on the key frames
        `source` (a finer grid's: binned to this one) and applied to `keys`. False where no flow can
        be computed (fewer than two key frames, images under MIN_FLOW_SIZE_PX)."""
        from rngcam.recon.methods.baselines import BaselineInputError, interp_warps
        from rngcam.recon.methods.rife import RifeUnavailableError, rife_warps

        if min(source.shape[-2:]) < MIN_FLOW_SIZE_PX:  # as _base_video: no flow of either kind that small
            return False
        args = (source.detach().float().cpu().numpy(), self.problem.gs_times_s, self.problem.frame_times_s)
        warps = None
        if kind != "keys_interp" and keys.shape[0] in (1, 3):
            try:
                with torch.random.fork_rng(devices=[]):  # building the network draws random numbers
                    warps, name = rife_warps(*args, model=self.base_model,
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
        self.base_model = _resolved_model(self.base_model) if name == "keys_rife" else None
        name += HDV3_SUFFIX if self.base_model == "hdv3" else ""
        order = np.argsort(self.problem.gs_times_s, kind="stable")  # the warps' keys are sorted by time
        self.key_images = keys[:, order].permute(1, 0, 2, 3).to(self.device, torch.float32).contiguous()  # (G, C, H, W)
        self.key_left = torch.from_numpy(warps.left).to(self.device)
        flows = torch.from_numpy(np.concatenate([warps.flow0, warps.flow1], axis=-1))
        h, w = source.shape[-2:]
        px = torch.tensor([(w - 1) / 2, (h - 1) / 2]).clamp_min(0.5).repeat(2)  # the source grid's pixels
        flows, w0 = flows / px, torch.from_numpy(warps.weight0)  # coordinate units: the same on every grid
        if source is not keys:
            flows = bin_space(flows.permute(0, 3, 1, 2), self.H, self.W).permute(0, 2, 3, 1)
            w0 = bin_space(w0, self.H, self.W)
        self.key_flow = flows.to(self.device, torch.float32).contiguous()  # (K, H, W, 4)
        w0 = w0.to(self.device, torch.float32).clamp(1e-6, 1 - 1e-6)
        self.key_logit = torch.log(w0) - torch.log1p(-w0)
        self.base_source = name
        return True



def _rife_model_of(kind: str) -> tuple[str, str | None]:
    """A dynamic base without its RIFE-model suffix, and that model ("hdv3"; None: the default)."""
    if kind.endswith(HDV3_SUFFIX):
        return kind[:-len(HDV3_SUFFIX)], "hdv3"
    return kind, None


def _resolved_model(model: str | None) -> str:
    from rngcam.recon.methods.rife import resolve_model

    return resolve_model(model)[0]


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
    from rngcam.recon.methods.baselines import interp

    frames = keys.detach().float().cpu().numpy()
    if kind in ("video", "rife") and frames.shape[0] in (1, 3) and min(frames.shape[-2:]) >= MIN_FLOW_SIZE_PX:
        from rngcam.recon.methods.rife import RifeUnavailableError, rife

        try:
            with torch.random.fork_rng(devices=[]):  # building the network draws random numbers
                return torch.from_numpy(rife(frames, gs_times_s, frame_times_s, model=model, device=device)), "rife", ""
        except RifeUnavailableError as exc:
            if kind == "rife":
                raise
            why = _first_line(exc)
    else:
        why = ""
    return torch.from_numpy(np.asarray(interp(frames, gs_times_s, frame_times_s), np.float32)), "interp", why


