"""What one STFM fit sees of its problem: the grid's coordinates, the measurements' weights, masks and
the physics operators (rngcam.physics.operators), on the fit's device."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.recon.methods.stfm.fields import knots


def chunks(idx: Tensor, size: int) -> list[Tensor]:
    """`idx` in pieces of at most `size` (frames evaluated with one autograd graph)."""
    return [idx[i:i + size] for i in range(0, len(idx), size)] if len(idx) else []


def sorted_sample(n: int, k: int, generator: torch.Generator) -> np.ndarray:
    """k of range(n) without replacement, sorted, on the host: torch.randperm's first k (one draw of
    `generator`), the rest in numpy (no tensor operations)."""
    return np.sort(torch.randperm(n, generator=generator).numpy()[:k])


def to_device(idx: Tensor, device: torch.device) -> Tensor:
    """A host tensor (a step's sampled indices) on `device`; to a GPU through pinned memory without
    waiting (a plain copy would wait for everything queued before it)."""
    if idx.device == device:
        return idx
    if device.type != "cuda" or idx.device.type != "cpu":
        return idx.to(device)
    return idx.pin_memory().to(device, non_blocking=True)


def _axis(n: int, device) -> Tensor:
    return torch.linspace(-1.0, 1.0, n, device=device) if n > 1 else torch.zeros(1, device=device)


class FitGrid:
    """The problem as one fit sees it. Coordinates run over [-1, 1] on each axis (`xs`, `ys`, `ts`);
    `w_rs`/`w_gs` are the exposure weights (with host copies: which frames a step's rows and windows
    see, without waiting for a GPU); `rs_op`/`gs_op` the forward model; the `*_valid` masks zero the
    saturated pixels, which carry no linear information. The RS weights and operator are rebuilt where
    the fit learns the line time (rngcam.recon.methods.stfm.learned.LineTime.sync)."""

    def __init__(self, problem, parts, gs_anchor: str, frame_chunk: int, device: torch.device, config):
        """`config`: the fit stage's (stage_configs.EvaluationConfig: where the fields are decoded)."""
        p, dev = problem, device
        self.problem, self.device, self.frame_chunk = p, dev, frame_chunk
        self.C, self.K, self.H, self.W = p.shape
        self.xs, self.ys, self.ts = _axis(self.W, dev), _axis(self.H, dev), _axis(self.K, dev)
        self.xs_mean, self.ys_mean = (_axis(min(n, config.translation_mean_points), dev) for n in (self.W, self.H))
        self.xs_knots, self.ys_knots = (knots(a, config.motion_knot_px) for a in (self.xs, self.ys))
        self.canonical_knots = [knots(a, config.canonical_knot_px) for a in (self.xs, self.ys)]
        self.canonical_stride = round(1 / config.canonical_knot_px)  # pixels lie on every this-many knots
        self.mask = None if p.mask is None else p.mask.to(dev, torch.float32)
        self.px_per_unit = torch.tensor([(self.W - 1) / 2, (self.H - 1) / 2], device=dev).clamp_min(0.5)
        self.w_rs_host = p.rs_weights.to("cpu", torch.float32)
        self.w_rs_numpy = self.w_rs_host.numpy()
        self.w_rs = self.w_rs_host.to(dev)
        # Held-out split (rngcam.recon.problem): fit only the training rows and GS pixels.
        self.rs_rows_fit = (torch.arange(self.H) if p.rs_train_rows is None
                            else torch.nonzero(p.rs_train_rows.cpu()).flatten())
        fit = p.gs_fit_mask() if p.b_gs is not None else None
        self.gs_fit = None if fit is None else fit.to(dev, torch.float32)
        self.w_gs_host = p.gs_weights.to("cpu", torch.float32)
        self.w_gs = self.w_gs_host.to(dev)
        self.gs_frames = torch.nonzero(self.w_gs.sum(0) > 0).flatten() if parts.gs else \
            torch.zeros(0, dtype=torch.long, device=dev)
        self.gs_frames_host = self.gs_frames.cpu()
        self.rs_op = RollingShutter(p.psf, self.w_rs, self.W, self.C)
        self.gs_op = GlobalShutter(self.w_gs, self.C, (self.H, self.W))
        rs_valid, gs_valid = p.rs_valid_mask(), p.gs_valid_mask()
        self.rs_valid = None if rs_valid is None else rs_valid.to(dev, torch.float32)
        self.gs_valid = None if gs_valid is None else gs_valid.to(dev, torch.float32)
        self.anchor_p = None
        if parts.gs and gs_anchor == "hard":
            w = self.w_gs[:, self.gs_frames].double()  # (G, S)
            self.anchor_p = (torch.linalg.pinv(w @ w.t()) @ w).t().float()  # (S, G) = W^T (W W^T)^-1

    def rs_frames(self, rows: Tensor) -> Tensor:
        """Frames the RS rows `rows` see (their weights' non-zero columns), on the host."""
        return torch.nonzero(self.w_rs_host[rows.cpu()].sum(0) > 0).flatten()

    def set_rs_weights(self, weights: Tensor) -> None:
        """The RS rows' weights (H, K) as the fit now has them (a learned line time), and the operator."""
        self.w_rs_host = weights.to("cpu", torch.float32)
        self.w_rs_numpy = self.w_rs_host.numpy()
        self.w_rs = self.w_rs_host.to(self.device)
        self.rs_op = self.rs_op.with_weights(self.w_rs)

    def gs_centre_frames(self):
        """Fractional frame index of each GS exposure's centre of mass (numpy, one a GS frame)."""
        w = self.w_gs.double().cpu()
        k = torch.arange(self.K, dtype=torch.float64) + 0.5
        return ((w * k).sum(1) / w.sum(1).clamp_min(1e-12) - 0.5).numpy()

    def blend_weights(self, times: Tensor) -> Tensor:
        """(K, G) cross-fade weights of the key frames (centres `times`, in frames) per frame."""
        order = torch.argsort(times)
        t = times[order]
        k = torch.arange(self.K, device=self.device, dtype=torch.float32)
        weights = torch.zeros(self.K, len(t), device=self.device)
        if len(t) == 1:
            weights[:, 0] = 1
        else:
            right = torch.searchsorted(t, k).clamp(1, len(t) - 1)
            left = right - 1
            a = ((k - t[left]) / (t[right] - t[left]).clamp_min(1e-6)).clamp(0, 1)
            rows = torch.arange(self.K, device=self.device)
            weights[rows, order[left]] = 1 - a
            weights[rows, order[right]] += a
        return weights
