"""The plug-and-play prior's denoiser: FFDNet on 2-D slices of a video (frames, x-t or y-t slices),
a chunk of slices at a time, on sRGB-encoded values; 2-D TV where FFDNet's weights are missing."""

from __future__ import annotations

import torch
from torch import Tensor

from rngcam.physics import tv_prox as tv
from rngcam.recon.nets import ffdnet


def _srgb(x: Tensor) -> Tensor:
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def _linear(y: Tensor) -> Tensor:
    y = y.clamp(0, 1)
    return torch.where(y <= 0.04045, y / 12.92, ((y + 0.055) / 1.055) ** 2.4)


class Denoiser:
    """D(video, sigma) applied to 2-D slices of a (C, K, H, W) video, a chunk of slices at a time
    (memory: `chunk` frames' worth of activations; one x-t slice alone exceeds that only when K >
    chunk x H).

    FFDNet when its weights are installed, else 2-D TV (tv.prox_tv_nonneg without a time term)."""

    def __init__(self, device: str, chunk: int):
        self.chunk, self.note = chunk, ""
        try:
            self.net = ffdnet.load_ffdnet(device=device)
            self.name = "ffdnet"
        except ffdnet.DenoiserUnavailableError as missing:
            self.net, self.name = None, "tv2d"
            self.note = (f"{missing}; pnp denoises with 2-D TV instead ({TV_FALLBACK_COST})")

    @torch.no_grad()
    def __call__(self, video: Tensor, sigma: float, kind: str, scale: float) -> Tensor:
        c = video.shape[0]
        # images (N, C, h, w): frames, or x-t slices (one per row y), or y-t slices (one per column x)
        perm = {"xy": (1, 0, 2, 3), "xt": (2, 0, 1, 3), "yt": (3, 0, 1, 2)}[kind]
        images = video.permute(*perm)
        out = torch.empty_like(video)
        out_images = out.permute(*perm)  # written slice by slice: no second video-sized copy
        # As many slices per pass as hold the pixels of `chunk` frames: the denoiser's working
        # memory stays that of `chunk` frames whatever the slice shape (a x-t slice has K x W pixels).
        frame_px = video.shape[-1] * video.shape[-2]
        n = max(1, self.chunk * frame_px // (images.shape[-1] * images.shape[-2]))
        for start in range(0, images.shape[0], n):
            out_images[start:start + n] = self._denoise(images[start:start + n], sigma, scale, c)
        return out

    def _denoise(self, images: Tensor, sigma: float, scale: float, c: int) -> Tensor:
        if self.net is None:
            # TV weight ~ noise std: a rough match of strength in linear units
            return tv.prox_tv_nonneg(images.transpose(0, 1), sigma * scale, 0.0).transpose(0, 1)
        x = _srgb(images / scale)
        if c == 1:
            x = x.expand(-1, 3, -1, -1)
        y = self.net(x.float(), sigma).to(images.dtype)
        if c == 1:
            y = y.mean(1, keepdim=True)
        return _linear(y) * scale


# What the TV fallback costs against FFDNet (bench/pnp_compare.md).
TV_FALLBACK_COST = "a weaker prior: 1.4 dB lower on smoke's intermediate frames at 64 px"
