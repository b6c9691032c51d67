"""What both RIFE networks (rngcam.recon.methods.rife: HDv3, rngcam.recon.nets.rife4: 4.x) share: the error
raised when their weights are not installed, and the backward warp of their flows."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rngcam.errors import RngcamError


class RifeUnavailableError(RngcamError):
    """The RIFE weights are not installed."""


def backward_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample image (N, C, H, W) at x + flow(x) (pixels), bilinear, borders replicated."""
    n, _, h, w = flow.shape
    xs = torch.linspace(-1.0, 1.0, w, device=flow.device).view(1, 1, w).expand(n, h, w)
    ys = torch.linspace(-1.0, 1.0, h, device=flow.device).view(1, h, 1).expand(n, h, w)
    gx = xs + flow[:, 0] / ((w - 1.0) / 2.0)
    gy = ys + flow[:, 1] / ((h - 1.0) / 2.0)
    return F.grid_sample(image, torch.stack((gx, gy), -1), mode="bilinear",
                         padding_mode="border", align_corners=True)
