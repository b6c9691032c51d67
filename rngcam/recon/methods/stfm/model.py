"""STFM's fields and the video they make: static image, motion, dynamic colour and alpha."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rngcam.recon.methods.stfm.fields import field_on_grid, interpolate_grid, make_field, translate_image
from rngcam.recon.methods.stfm.grid import chunks


def _inverse_softplus(y: Tensor) -> Tensor:
    """x with softplus(x) = y (y clamped to >= 1e-4): y + log(1 - exp(-y)), stable."""
    y = y.clamp_min(1e-4)
    return y + torch.log(-torch.expm1(-y))


class FieldModel:
    """STFM's fields on one grid (rngcam.recon.methods.stfm.grid.FitGrid) and the frames they make, with
    the dynamic base they correct (bases.DynamicBase), the gains it is scaled by and the GS-to-RS pose
    that takes the frames to RS coordinates (learned.Gains, learned.Pose)."""

    def __init__(self, grid, parts, resolved, gs_anchor: str, base, gains, pose, problem, preset: dict):
        self.grid, self.parts, self.resolved, self.gs_anchor = grid, parts, resolved, gs_anchor
        self.base, self.gains, self.pose, self.problem = base, gains, pose, problem
        self.C, self.K, self.H, self.W = grid.C, grid.K, grid.H, grid.W
        kind_s, cfg_s = preset["static"]
        kind_m, cfg_m = preset["motion"]
        kind_d, cfg_d = preset["dynamic"]
        self.fields = nn.ModuleDict()
        self._canonical_now: Tensor | None = None  # the decoded canonical image inside decoded_once
        # constants as tensors (a number costs a conversion at every operation, forward and backward)
        self._one = torch.ones((), device=grid.device)
        self._motion_px: Tensor | None = None
        self._mean_points = torch.tensor(float(len(grid.xs_mean) * len(grid.ys_mean)), device=grid.device)
        if parts.static:
            self.fields["static"] = make_field(kind_s, 2, self.C, **cfg_s)
        if parts.motion:
            keys = base.key_warps
            self.fields["motion"] = make_field(kind_m, 3, 4 if keys else 2, **cfg_m)
            dims = 3 if resolved.dynamic_time else 2
            if dims == 2:
                cfg_d = {k: v for k, v in cfg_d.items() if k != "time_resolutions"}
            self.fields["dynamic"] = make_field(kind_d, dims, self.C + (2 if keys else 1), **cfg_d)
            if base.source is not None and kind_d == "planes":  # start exactly at the base
                head = self.fields["dynamic"].decoder[-1]
                with torch.no_grad():
                    for ch in self.correction_channels():
                        head.weight[ch] = 0
                        head.bias[ch] = 0
            if kind_m == "planes":  # start without motion; gradients still reach every plane
                head = self.fields["motion"].decoder[-1]
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)
        self.fields.to(grid.device)


    # ------------------------------------------------------------------ the model

    def static(self) -> Tensor:
        """(C, H, W) static image."""
        raw = field_on_grid(self.fields["static"], [self.grid.xs, self.grid.ys])  # (H, W, C)
        return F.softplus(raw).permute(2, 0, 1)

    def motion(self, idx: Tensor, per_pixel: bool = True) -> Tensor:
        """(n, H, W, 2) displacement in coordinate units at frames idx; a translation as (n, 1, 1, 2)
        where not `per_pixel`."""
        if self.resolved.motion_model == "translation":  # one rigid layer: the field's mean over the frame
            u = field_on_grid(self.fields["motion"], [self.grid.xs_mean, self.grid.ys_mean, self.grid.ts], idx)
            u = u.sum(dim=(1, 2), keepdim=True).div(self._mean_points)  # the mean, as torch computes it
            return u.expand(len(idx), self.H, self.W, u.shape[-1]) if per_pixel else u
        u = field_on_grid(self.fields["motion"], [self.grid.xs_knots, self.grid.ys_knots, self.grid.ts], idx)
        return interpolate_grid(u, [self.grid.xs_knots, self.grid.ys_knots], [self.grid.xs, self.grid.ys])

    def per_pixel(self, u: Tensor) -> Tensor:
        """Motion (n, H, W, c) of `motion(idx, per_pixel=False)`'s (a translation's (n, 1, 1, c) expanded)."""
        return u.expand(u.shape[0], self.H, self.W, u.shape[-1]) if u.shape[1:3] != (self.H, self.W) else u

    def correction_channels(self) -> list[int]:
        """Dynamic-field outputs that correct a base (zero at the start): colour, and with
        base "keys" the blend logit."""
        return list(range(self.C)) + ([self.C + 1] if self.base.key_warps else [])

    def motion_px(self) -> Tensor:
        """Pixels per coordinate unit for each motion component."""
        if self._motion_px is None:  # kept: a repeat is a dozen recorded operations a step
            self._motion_px = self.grid.px_per_unit.repeat(2) if self.base.key_warps else self.grid.px_per_unit
        return self._motion_px

    def dynamic_at(self, u: Tensor, idx: Tensor) -> tuple[Tensor, Tensor]:
        """Dynamic colour (C, n, H, W) and alpha (1, n, H, W) of frames idx under the motion u
        (n, H, W, 2). With a base (key frames or a video) and a field over (x, y, t), the motion
        moves the base and the field corrects it where it sits; otherwise the field (the canonical
        image where it is 2-D, with the base where there is one) is read at the moved points."""
        n = u.shape[0]
        if self.translated_dynamic():  # one translation per frame: the decoded image moved
            image = self._canonical_now if self._canonical_now is not None else self.canonical()
            raw = translate_image(image, [self.grid.xs, self.grid.ys], u[:, 0, 0, :2])
            raw = raw.permute(3, 0, 1, 2).contiguous()  # softplus on a strided view is slower, backward too
            return F.softplus(raw[:self.C]), torch.sigmoid(raw[self.C:])
        x = self.grid.xs.view(1, 1, -1) + u[..., 0]
        y = self.grid.ys.view(1, -1, 1) + u[..., 1]
        gain = self.gains.value()[:, None, None, None]
        if self.base.key_warps or (self.base.source is not None and self.resolved.dynamic_time):
            # On the pixel grid: read at the moved points (grid_sample's backward) it cost a video
            # member's step more, for the same video (bench/convergence.md, "the fast preset's motion on knots").
            axes = [self.grid.xs, self.grid.ys, self.grid.ts]
            raw = field_on_grid(self.fields["dynamic"], axes, idx).permute(3, 0, 1, 2)
            base = self.base.keys_at(u, raw[self.C + 1], idx) if self.base.key_warps else self.base.at(x, y, idx)
            return F.softplus(raw[:self.C] + _inverse_softplus(base * gain)), torch.sigmoid(raw[self.C:self.C + 1])
        coords = [x, y]
        if self.resolved.dynamic_time:
            coords.append(self.grid.ts[idx].view(-1, 1, 1).expand_as(x))
        raw = self.fields["dynamic"](torch.stack(coords, dim=-1).reshape(-1, len(coords)))
        raw = raw.reshape(n, self.H, self.W, self.C + 1).permute(3, 0, 1, 2).contiguous()
        colour = raw[:self.C]
        if self.base.source is not None:  # a 2-D field: the canonical image moves with the base
            colour = colour + _inverse_softplus(self.base.at(x, y, idx) * gain)
        return F.softplus(colour), torch.sigmoid(raw[self.C:])

    def translated_dynamic(self) -> bool:
        """Whether the dynamic field is 2-D, moved by one translation per frame, with no base video."""
        return (self.parts.motion and self.resolved.motion_model == "translation" and not self.resolved.dynamic_time
                and self.base.source is None)

    def canonical(self) -> Tensor | None:
        """The translated dynamic field's decoded image (R_y, R_x, C + 1), which every frame moves
        (None: the dynamic field is not translated)."""
        if not self.translated_dynamic():
            return None
        return field_on_grid(self.fields["dynamic"], self.grid.canonical_knots)

    def canonical_at_pixels(self) -> Tensor | None:
        """The decoded canonical image at the pixels, which lie on its knots (None: none decoded now,
        or an axis of one pixel, whose centre is not on the knots' stride)."""
        image, step = self._canonical_now, self.grid.canonical_stride
        if image is None or min(self.H, self.W) < 2:
            return None
        return image[::step, ::step]

    @contextmanager
    def decoded_once(self, image: Tensor | None = None):
        """Inside: every frame evaluation moves one decoded canonical image, `image` (a step's leaf)
        or, without one, the image decoded now."""
        previous = self._canonical_now
        self._canonical_now = self.canonical() if image is None else image
        try:
            yield
        finally:
            self._canonical_now = previous

    def frames(self, idx: Tensor, static: Tensor | None = None, motion: Tensor | None = None) -> Tensor:
        """Video frames idx (C, n, H, W), before any hard GS anchoring (zero outside the mask).

        `static` may pass in the static image already evaluated for this step, `motion` the motion at
        idx (`motion(idx, per_pixel=False)`)."""
        n = len(idx)
        if self.parts.static and static is None:
            static = self.static()
        if not self.parts.motion:
            v = static[:, None].expand(self.C, n, self.H, self.W)
        else:
            u = self.motion(idx) if motion is None else self.per_pixel(motion)
            colour, alpha = self.dynamic_at(u, idx)
            v = colour if not self.parts.static else alpha * static[:, None] + (self._one - alpha) * colour
        return v if self.grid.mask is None else v * self.grid.mask

    def anchored(self, v_gs: Tensor) -> Tensor:
        """Hard anchoring of the GS-window frames (C, S, H, W) onto Lambda b_G."""
        target = self.gains.value()[:, None, None, None] * self.problem.b_gs
        windows = torch.arange(self.grid.w_gs.shape[0], device=self.grid.device)
        miss = target - self.grid.gs_op.A_frames(v_gs, windows, self.grid.gs_frames)
        if self.grid.mask is not None:
            miss = miss * self.grid.mask
        if self.grid.gs_fit is not None:  # exact while GS exposures do not overlap in time
            miss = miss * self.grid.gs_fit
        if self.grid.gs_valid is not None:  # saturated GS pixels say nothing: left as the fields make them
            miss = miss * self.grid.gs_valid
        return v_gs + torch.einsum("sg,cghw->cshw", self.grid.anchor_p, miss)

    def gs_window(self) -> Tensor:
        v = self.frames(self.grid.gs_frames)
        return self.anchored(v) if self.gs_anchor == "hard" else v

    def video_frames(self, idx: Tensor, native: bool = False) -> Tensor:
        """Frames idx of the video as output, in RS coordinates (`native`: the fields' own, the GS
        camera's), with hard anchoring where it applies."""
        if not native and self.pose.learned:
            return self.pose.rs_view(self.frames(idx))  # learn_pose: soft anchoring
        if self.gs_anchor != "hard" or not self.parts.gs:
            return self.frames(idx)
        inside = torch.isin(idx, self.grid.gs_frames)
        if not bool(inside.any()):
            return self.frames(idx)
        window = self.gs_window()
        out = self.frames(idx)
        out[:, inside] = window[:, torch.searchsorted(self.grid.gs_frames, idx[inside])]
        return out


    def components(self) -> dict[str, np.ndarray]:
        """static (C, H, W), alpha (1, K, H, W) and motion (2, K, H, W, in pixels) as numpy."""
        dev = self.grid.device
        static = self.static() if self.parts.static else torch.zeros(self.C, self.H, self.W, device=dev)
        alpha = torch.ones(1, self.K, self.H, self.W, device=dev) if self.parts.static else \
            torch.zeros(1, self.K, self.H, self.W, device=dev)
        motion = torch.zeros(2, self.K, self.H, self.W, device=dev)
        if self.parts.motion:
            for idx in chunks(torch.arange(self.K, device=dev), self.grid.frame_chunk):
                u = self.motion(idx)
                total = u[..., :2] + (self.base.key_flow[idx][..., :2] if self.base.key_warps else 0)
                motion[:, idx] = (total * self.grid.px_per_unit).permute(3, 0, 1, 2)
                if self.parts.static:
                    alpha[:, idx] = self.dynamic_at(u, idx)[1]
        return {"static": static.cpu().numpy(), "alpha": alpha.cpu().numpy(), "motion": motion.cpu().numpy()}
