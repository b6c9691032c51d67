"""STFM's initialisation from the GS frames (static background, alpha, dynamic colour, motion)."""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rngcam.recon.methods.baselines import linear_to_srgb
from rngcam.recon.methods.stfm.fields import field_on_grid
from rngcam.recon.methods.stfm.motion_search import object_mask, translation_track
from rngcam.recon.methods.stfm.settings import MIN_FLOW_SIZE_PX


class GSInit:
    """Fits a new fit's fields to what the GS frames say before the main fit (`run`)."""

    def __init__(self, fit):
        self.fit, self.model, self.grid = fit, fit.model, fit.grid
        self.parts, self.resolved, self.settings = fit.parts, fit.resolved, fit.settings
        self.fields, self.K, self.H, self.W, self.C = fit.model.fields, fit.K, fit.H, fit.W, fit.C
        self.device, self.xs, self.ys = fit.device, fit.grid.xs, fit.grid.ys
        self.config = fit.fit_config

    def run(self) -> None:
        """Fit the fields to what the GS frames say before the main fit.

        Static field: the per-pixel median of the key frames (the background). Alpha: one where
        every key frame agrees with that background. With a time-dependent dynamic field, its
        colour is fitted to the cross-fade of the key frames (the fit starts at the blend
        baseline); otherwise to the key frame nearest the middle, and the motion field to DIS
        optical flow between that frame and the others, linearly interpolated in time."""
        c = self.config
        steps = c.init_steps
        v = self.fit.problem.gs_images(gains=True).float()  # (C, G, H, W): Lambda b_G / exposure
        background = v.median(dim=1).values
        times = torch.as_tensor(self.grid.gs_centre_frames(), device=self.device).float()
        middle = int(torch.argmin((times - (self.K - 1) / 2).abs()))
        static_from = self.fit.static_from
        if self.parts.static and static_from is not None and "static" in static_from.model.fields:
            self.fields["static"].load_state_dict(static_from.model.fields["static"].state_dict())
        elif self.parts.static:
            _fit_image(self.fields["static"], self.xs, self.ys, background, steps, c)
        if not self.parts.motion:
            return
        alpha = None
        if self.parts.static:
            change = (v - background[:, None]).abs().mean(0).amax(0)  # (H, W)
            thr = c.layer_change * float(background.mean()) + 1e-6  # as motion_search.object_mask
            alpha = (1 - change / thr).clamp(0, 1)
        if self.resolved.dynamic_time:
            self._fit_dynamic_to_blend(v, times, alpha, steps)
        elif self.resolved.motion_init == "search":
            self._init_by_search(v[:, middle], background, steps)
        else:
            _fit_image(self.fields["dynamic"], self.xs, self.ys, v[:, middle], steps, c, alpha)
            self._fit_motion(self._key_flows(v, middle), times, steps)

    def _init_by_search(self, layer: Tensor, background: Tensor, steps: int) -> None:
        """The canonical dynamic image is the middle key frame; alpha is where that frame (not every
        key frame: the image moves) differs from the background; the motion is the per-frame
        translation of that image found by rngcam.recon.methods.stfm.motion_search."""
        obj = object_mask(layer, background, self.config.layer_change)  # 1 on the moving object
        alpha = 1 - obj if self.parts.static else None
        _fit_image(self.fields["dynamic"], self.xs, self.ys, layer, steps, self.config, alpha)
        row_gains = self.fit.state.row_gain_search
        if row_gains:
            self.fit.notes_at_build.append("motion search: each RS row scored after its own gain")
        if self.fit.state.search_turn_scale != 1:
            self.fit.notes_at_build.append(f"motion search: turn penalty x{self.fit.state.search_turn_scale:g}")
        track = translation_track(self.fit, background, layer, obj, row_gains=row_gains).to(self.device)  # (K, 2) px
        self.fit.motion_track_px = track
        # The dynamic field is sampled at x + u: a layer moved by d has u = -d (coordinate units).
        target = (-track / self.grid.px_per_unit)[:, None, None, :].expand(self.K, self.H, self.W, 2)
        c = self.config  # a track that turns round: more steps
        self._fit_motion_to(target, c.init_search_step_factor * steps, frames_per_step=c.init_search_frames)

    def _fit_dynamic_to_blend(self, v: Tensor, times: Tensor, alpha: Tensor | None, steps: int) -> None:
        weights = self.grid.blend_weights(times)  # (K, G)
        field = self.fields["dynamic"]
        opt = torch.optim.Adam(field.parameters(), lr=self.config.init_lr)
        gen = torch.Generator(device="cpu").manual_seed(self.settings.seed + 2)
        for _ in range(steps):
            idx = torch.randperm(self.K, generator=gen)[:self.config.init_frames_per_step].to(self.device)
            opt.zero_grad()
            raw = field_on_grid(field, [self.xs, self.ys, self.grid.ts], idx).permute(3, 0, 1, 2)
            if self.model.base.source is not None:  # the colour is already the base video: keep it
                loss = raw[self.model.correction_channels()].square().mean()
            else:
                target = torch.einsum("kg,cghw->ckhw", weights[idx], v)
                loss = (F.softplus(raw[:self.C]) - target).square().mean()
            if alpha is not None:
                loss = loss + self.config.init_alpha_weight * (torch.sigmoid(raw[self.C]) - alpha).square().mean()
            loss.backward()
            opt.step()

    def _key_flows(self, v: Tensor, middle: int) -> Tensor:
        """(G, H, W, 2) displacement (coordinate units) with frame_g(x) ~ frame_middle(x + u)."""
        g = v.shape[1]
        flows = torch.zeros(g, self.H, self.W, 2, device=self.device)
        if min(self.H, self.W) < MIN_FLOW_SIZE_PX:
            return flows
        frames = v.detach().cpu().numpy()
        scale = max(float(frames.max()), 1e-12)
        grey = [_grey_u8(frames[:, i], scale) for i in range(g)]
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        for i in range(g):
            if i != middle:
                try:
                    f = dis.calc(grey[i], grey[middle], None)
                except cv2.error:  # DIS refuses some tiny images: start without motion
                    return flows.zero_()
                flows[i] = torch.from_numpy(f).to(self.device) / self.grid.px_per_unit
        return flows

    def _fit_motion(self, flows: Tensor, times: Tensor, steps: int) -> None:
        """Fit the motion field to the key-frame flows, linearly interpolated in time."""
        if float(flows.abs().max()) == 0:
            return
        self._fit_motion_to(torch.einsum("kg,ghwc->khwc", self.grid.blend_weights(times), flows), steps)

    def _fit_motion_to(self, target: Tensor, steps: int, frames_per_step: int | None = None) -> None:
        """Fit the motion field to a displacement (K, H, W, 2) in coordinate units."""
        params = list(self.fields["motion"].parameters())
        opt = torch.optim.Adam(params, lr=self.config.init_lr)
        frames_per_step = frames_per_step or self.config.init_frames_per_step
        gen = torch.Generator(device="cpu").manual_seed(self.settings.seed + 1)
        for _ in range(steps):
            idx = torch.randperm(self.K, generator=gen)[:frames_per_step].to(self.device)
            opt.zero_grad()
            loss = (self.model.motion(idx) - target[idx]).square().mean()
            loss.backward()
            opt.step()



def _grey_u8(frame: np.ndarray, scale: float) -> np.ndarray:
    # Rec. 709 luma weights (the physics of a grey image, not a tuning)
    grey = frame.mean(0) if frame.shape[0] != 3 else 0.2126 * frame[0] + 0.7152 * frame[1] + 0.0722 * frame[2]
    return np.round(linear_to_srgb(grey / scale) * 255).astype(np.uint8)


def _fit_image(module: nn.Module, xs: Tensor, ys: Tensor, image: Tensor, steps: int, config,
               alpha: Tensor | None = None) -> None:
    """Fit a 2-D field so softplus(colour) = image (C, H, W) (and sigmoid(last) = alpha), at the step and
    alpha weight of `config` (the fit stage's)."""
    params = list(module.parameters())
    opt = torch.optim.Adam(params, lr=config.init_lr)
    c = image.shape[0]
    for _ in range(steps):
        opt.zero_grad()
        raw = field_on_grid(module, [xs, ys]).permute(2, 0, 1)
        loss = (F.softplus(raw[:c]) - image).square().mean()
        if alpha is not None:
            loss = loss + config.init_alpha_weight * (torch.sigmoid(raw[c]) - alpha).square().mean()
        loss.backward()
        opt.step()


