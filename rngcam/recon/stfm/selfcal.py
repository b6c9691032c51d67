"""STFM's self-calibration: the GS prediction warped by a GS-to-RS similarity refined during the
fit (rngcam.recon.selfcal has the registration and why it estimates the transform)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rngcam.recon import selfcal


class SelfCalibration:
    """Part of STFM: the GS warp S (the GS camera sees the video at S(p)), its schedule and report."""

    def _build_selfcal(self) -> None:
        self.gs_warp = np.eye(3)
        self._gs_warp_t: Tensor | None = None
        self.selfcal_log: list[dict] = []

    def warp_gs(self, pred: Tensor) -> Tensor:
        """GS frames (C, n, H, W) predicted from the video, as the GS camera sees them."""
        if self._gs_warp_t is None:
            return pred
        return selfcal.warp(pred, self._gs_warp_t)

    def set_gs_warp(self, matrix) -> None:
        self.gs_warp = np.asarray(matrix, np.float64)
        self._gs_warp_t = None if selfcal.is_identity(self.gs_warp) else \
            torch.as_tensor(self.gs_warp, dtype=torch.float32, device=self.device)
        self._cache = None

    @torch.no_grad()
    def self_calibrate(self, free: int = 4) -> dict:
        """Register the current estimate against the RS image and compose the GS warp with it."""
        video = self.estimate()
        valid = self.rs_valid if self.rs_valid is not None else None
        with torch.enable_grad():
            t, before, after = selfcal.register_to_rs(video, lambda v: self.rs_op.A(v), self.problem.b_rs,
                                                      valid, free=free)
        new = np.linalg.inv(t) @ self.gs_warp
        entry = {"step": self.steps, "rs_residual_before": before, "rs_residual_after": after,
                 **selfcal.describe(new)}
        self.selfcal_log.append(entry)
        self.set_gs_warp(new)
        return entry
