"""STFM's fields and the video they make: static image, motion, dynamic colour and alpha."""

from __future__ import annotations

from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rngcam.errors import ConfigError
from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.recon.methods.selfcal import inside, pose_matrix, warp, warp_shift
from rngcam.recon.methods.stfm.fields import field_on_grid, interpolate_grid, knots, make_field, translate_image


def _chunks(idx: Tensor, size: int) -> list[Tensor]:
    return [idx[i:i + size] for i in range(0, len(idx), size)] if len(idx) else []


def _to_device(idx: Tensor, device: torch.device) -> Tensor:
    """A host tensor (a step's sampled indices) on `device`; to a GPU through pinned memory without
    waiting (a plain copy would wait for everything queued before it)."""
    if idx.device == device or device.type != "cuda" or idx.device.type != "cpu":
        return idx.to(device)
    return idx.pin_memory().to(device, non_blocking=True)


# A translation is the motion field's mean over this many points per axis of the frame (at most),
# not over every pixel: the same family of motions (the mean of a field over a grid) for a fraction
# of the field's evaluations (bench/convergence.md, "the prior preset's translation averaged over 16 x 16 points").
TRANSLATION_MEAN_POINTS = 16
# A motion field is decoded on knots about this many pixels apart and interpolated bilinearly
# between them: its finest planes have knots 4 px apart, so a quarter of the decoder's points cut a
# fast step's time and not its result (bench/convergence.md, "the fast preset's motion on knots").
MOTION_KNOT_PX = 2
# The prior preset's canonical image is decoded on knots this many pixels apart, the pixel centres
# on them, and moved by bilinear interpolation (bench/convergence.md, "the prior preset decodes its
# canonical image once a step").
CANONICAL_KNOT_PX = 0.5


def _inverse_softplus(y: Tensor) -> Tensor:
    """x with softplus(x) = y (y clamped to >= 1e-4): y + log(1 - exp(-y)), stable."""
    y = y.clamp_min(1e-4)
    return y + torch.log(-torch.expm1(-y))


class FieldModel:
    """Part of STFM (rngcam.recon.methods.stfm.method): geometry, the fields, and frames of the video."""

    def _build_geometry(self) -> None:
        p, dev = self.problem, self.device

        def axis(n):
            return torch.linspace(-1.0, 1.0, n, device=dev) if n > 1 else torch.zeros(1, device=dev)

        self.xs, self.ys, self.ts = axis(self.W), axis(self.H), axis(self.K)
        self.xs_mean, self.ys_mean = (axis(min(n, TRANSLATION_MEAN_POINTS)) for n in (self.W, self.H))
        self.xs_knots, self.ys_knots = (knots(a, MOTION_KNOT_PX) for a in (self.xs, self.ys))
        self.canonical_knots = [knots(a, CANONICAL_KNOT_PX) for a in (self.xs, self.ys)]
        self.mask = None if p.mask is None else p.mask.to(dev, torch.float32)
        self.px_per_unit = torch.tensor([(self.W - 1) / 2, (self.H - 1) / 2], device=dev).clamp_min(0.5)
        # host copies of the weights: which frames a step's rows and windows see, without a GPU's answer
        self.w_rs_host = p.rs_weights.to("cpu", torch.float32)
        self.w_rs = self.w_rs_host.to(dev)
        # Held-out split (rngcam.recon.problem): fit only the training rows and GS pixels.
        self.rs_rows_fit = (torch.arange(self.H) if p.rs_train_rows is None
                            else torch.nonzero(p.rs_train_rows.cpu()).flatten())
        fit = p.gs_fit_mask() if p.b_gs is not None else None
        self.gs_fit = None if fit is None else fit.to(dev, torch.float32)
        self.w_gs_host = p.gs_weights.to("cpu", torch.float32)
        self.w_gs = self.w_gs_host.to(dev)
        self.gs_frames = torch.nonzero(self.w_gs.sum(0) > 0).flatten() if self.parts.gs else \
            torch.zeros(0, dtype=torch.long, device=dev)
        self.gs_frames_host = self.gs_frames.cpu()
        # The forward model is rngcam.physics.operators' (a step uses its row/frame restrictions).
        self.rs_op = RollingShutter(p.psf, self.w_rs, self.W, self.C)
        self.gs_op = GlobalShutter(self.w_gs, self.C, (self.H, self.W))
        # Saturated pixels carry no linear information: every data residual is multiplied by these.
        rs_valid, gs_valid = p.rs_valid_mask(), p.gs_valid_mask()
        self.rs_valid = None if rs_valid is None else rs_valid.to(dev, torch.float32)
        self.gs_valid = None if gs_valid is None else gs_valid.to(dev, torch.float32)
        if self.parts.gs and self.settings.gs_anchor == "hard":
            w = self.w_gs[:, self.gs_frames].double()  # (G, S)
            self.anchor_p = (torch.linalg.pinv(w @ w.t()) @ w).t().float()  # (S, G) = W^T (W W^T)^-1


    def _build_fields(self, preset: dict) -> None:
        kind_s, cfg_s = preset["static"]
        kind_m, cfg_m = preset["motion"]
        kind_d, cfg_d = preset["dynamic"]
        self.fields = nn.ModuleDict()
        self._canonical_now: Tensor | None = None  # the decoded canonical image inside _decoded_once
        if self.parts.static:
            self.fields["static"] = make_field(kind_s, 2, self.C, **cfg_s)
        if self.parts.motion:
            keys = self._key_warps
            self.fields["motion"] = make_field(kind_m, 3, 4 if keys else 2, **cfg_m)
            dims = 3 if self.resolved.dynamic_time else 2
            if dims == 2:
                cfg_d = {k: v for k, v in cfg_d.items() if k != "time_resolutions"}
            self.fields["dynamic"] = make_field(kind_d, dims, self.C + (2 if keys else 1), **cfg_d)
            if self.base_source is not None and kind_d == "planes":  # start exactly at the base
                head = self.fields["dynamic"].decoder[-1]
                with torch.no_grad():
                    for ch in self._correction_channels():
                        head.weight[ch] = 0
                        head.bias[ch] = 0
            if kind_m == "planes":  # start without motion; gradients still reach every plane
                head = self.fields["motion"].decoder[-1]
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)
        self.fields.to(self.device)
        wb = self.problem.white_balance
        start = torch.ones(self.C, device=self.device) if wb is None else wb.to(self.device).float()
        if not torch.all(start > 0):
            raise ConfigError(f"white balance gains must be > 0, got {start.tolist()}")
        self.log_gain = nn.Parameter(start.log())
        # The GS-to-RS transform S (the GS camera's pixel p sees the scene at S p), learned with the
        # fields where `learn_pose` (set with the optimiser): pose_matrix's parameters. The fields
        # live in the GS camera's coordinates, so that the GS term does not depend on S (else the
        # fields and S trade a shift along a flat valley that only the RS term tilts); the RS term
        # and the output video see the frames in RS coordinates, sampled at S^-1 q (_rs_view).
        self.gs_pose = nn.Parameter(torch.zeros(4, device=self.device))
        self.pose_free = torch.ones(4, device=self.device)  # 0: that value held at zero
        self.pose_radius = max(self.H, self.W) / 2
        self.learn_pose = False
        self._pose_inherited = False  # started from another fit's pose (start_pose, fields_from)
        self.pose_is_shift = False  # rotation and scale held at zero (learn_geometry "shift")


    # ------------------------------------------------------------------ the model

    def _static(self) -> Tensor:
        """(C, H, W) static image."""
        raw = field_on_grid(self.fields["static"], [self.xs, self.ys])  # (H, W, C)
        return F.softplus(raw).permute(2, 0, 1)

    def _motion(self, idx: Tensor, per_pixel: bool = True) -> Tensor:
        """(n, H, W, 2) displacement in coordinate units at frames idx; a translation as (n, 1, 1, 2)
        where not `per_pixel`."""
        if self.resolved.motion_model == "translation":  # one rigid layer: the field's mean over the frame
            u = field_on_grid(self.fields["motion"], [self.xs_mean, self.ys_mean, self.ts], idx)
            u = u.mean(dim=(1, 2), keepdim=True)
            return u.expand(len(idx), self.H, self.W, u.shape[-1]) if per_pixel else u
        u = field_on_grid(self.fields["motion"], [self.xs_knots, self.ys_knots, self.ts], idx)
        return interpolate_grid(u, [self.xs_knots, self.ys_knots], [self.xs, self.ys])

    @property
    def _key_warps(self) -> bool:
        return self.base_source in ("keys_rife", "keys_rife_hdv3", "keys_interp")

    def _correction_channels(self) -> list[int]:
        """Dynamic-field outputs that correct a base (zero at the start): colour, and with
        base "keys" the blend logit."""
        return list(range(self.C)) + ([self.C + 1] if self._key_warps else [])

    def _motion_px(self) -> Tensor:
        """Pixels per coordinate unit for each motion component."""
        return self.px_per_unit.repeat(2) if self._key_warps else self.px_per_unit

    def _keys_at(self, u: Tensor, blend_logit: Tensor, idx: Tensor) -> Tensor:
        """Base "keys": the two key frames around each frame idx warped by the interpolation's
        flows plus u (n, H, W, 4) and blended with its weights plus blend_logit (n, H, W)."""
        flow = self.key_flow.index_select(0, idx) + u
        left = self.key_left.index_select(0, idx)
        gx, gy = self.xs.view(1, 1, -1), self.ys.view(1, -1, 1)

        def warped(keys, f):
            grid = torch.stack([gx + f[..., 0], gy + f[..., 1]], dim=-1)
            return F.grid_sample(keys, grid, mode="bilinear", padding_mode="border", align_corners=True)

        w0 = warped(self.key_images.index_select(0, left), flow[..., :2])
        w1 = warped(self.key_images.index_select(0, left + 1), flow[..., 2:])
        m = torch.sigmoid(self.key_logit.index_select(0, idx) + blend_logit)[:, None]
        return (m * w0 + (1 - m) * w1).permute(1, 0, 2, 3)

    def _dynamic_at(self, u: Tensor, idx: Tensor) -> tuple[Tensor, Tensor]:
        """Dynamic colour (C, n, H, W) and alpha (1, n, H, W) of frames idx under the motion u
        (n, H, W, 2). With a base (key frames or a video) and a field over (x, y, t), the motion
        moves the base and the field corrects it where it sits; otherwise the field (the canonical
        image where it is 2-D, with the base where there is one) is read at the moved points."""
        n = u.shape[0]
        if self._translated_dynamic():  # one translation per frame: the decoded image moved
            image = self._canonical_now if self._canonical_now is not None else self._canonical()
            raw = translate_image(image, [self.xs, self.ys], u[:, 0, 0, :2])
            raw = raw.permute(3, 0, 1, 2).contiguous()  # softplus on a strided view is slower, backward too
            return F.softplus(raw[:self.C]), torch.sigmoid(raw[self.C:])
        x = self.xs.view(1, 1, -1) + u[..., 0]
        y = self.ys.view(1, -1, 1) + u[..., 1]
        gain = self._gain()[:, None, None, None]
        if self._key_warps or (self.base_source is not None and self.resolved.dynamic_time):
            # On the pixel grid: read at the moved points (grid_sample's backward) it cost a video
            # member's step more, for the same video (bench/convergence.md, "the fast preset's motion on knots").
            raw = field_on_grid(self.fields["dynamic"], [self.xs, self.ys, self.ts], idx).permute(3, 0, 1, 2)
            base = self._keys_at(u, raw[self.C + 1], idx) if self._key_warps else self._base_at(x, y, idx)
            return F.softplus(raw[:self.C] + _inverse_softplus(base * gain)), torch.sigmoid(raw[self.C:self.C + 1])
        coords = [x, y]
        if self.resolved.dynamic_time:
            coords.append(self.ts[idx].view(-1, 1, 1).expand_as(x))
        raw = self.fields["dynamic"](torch.stack(coords, dim=-1).reshape(-1, len(coords)))
        raw = raw.reshape(n, self.H, self.W, self.C + 1).permute(3, 0, 1, 2).contiguous()
        colour = raw[:self.C]
        if self.base_source is not None:  # a 2-D field: the canonical image moves with the base
            colour = colour + _inverse_softplus(self._base_at(x, y, idx) * gain)
        return F.softplus(colour), torch.sigmoid(raw[self.C:])

    def _translated_dynamic(self) -> bool:
        """Whether the dynamic field is 2-D, moved by one translation per frame, with no base video."""
        return (self.parts.motion and self.resolved.motion_model == "translation" and not self.resolved.dynamic_time
                and self.base_source is None)

    def _canonical(self) -> Tensor | None:
        """The translated dynamic field's decoded image (R_y, R_x, C + 1), which every frame moves
        (None: the dynamic field is not translated)."""
        if not self._translated_dynamic():
            return None
        return field_on_grid(self.fields["dynamic"], self.canonical_knots)

    def _canonical_at_pixels(self) -> Tensor | None:
        """The decoded canonical image at the pixels, which lie on its knots (None: none decoded now,
        or an axis of one pixel, whose centre is not on the knots' stride)."""
        image, step = self._canonical_now, round(1 / CANONICAL_KNOT_PX)
        if image is None or min(self.H, self.W) < 2:
            return None
        return image[::step, ::step]

    @contextmanager
    def _decoded_once(self, image: Tensor | None = None):
        """Inside: every frame evaluation moves one decoded canonical image, `image` (a step's leaf)
        or, without one, the image decoded now."""
        previous = self._canonical_now
        self._canonical_now = self._canonical() if image is None else image
        try:
            yield
        finally:
            self._canonical_now = previous

    def _base_at(self, x: Tensor, y: Tensor, idx: Tensor) -> Tensor:
        """The base video (C, n, H, W) of frames idx sampled at the points (x, y) (n, H, W)."""
        n = len(idx)
        if self.base_video is not None:
            grid = torch.stack([x, y], dim=-1)  # (n, H, W, 2)
            frames = self.base_video.index_select(1, idx).permute(1, 0, 2, 3).to(grid.dtype)  # (n, C, H, W)
            out = F.grid_sample(frames, grid, mode="bilinear", padding_mode="border", align_corners=True)
            out = out.permute(1, 0, 2, 3)
            return out if self.base_gains is None else out / self.base_gains[:, None, None, None]
        grid = torch.stack([x, y], dim=-1).reshape(1, n * self.H, self.W, 2)
        keys = F.grid_sample(self.base_keys, grid, mode="bilinear", padding_mode="border",
                             align_corners=True).view(self.C, -1, n, self.H, self.W)
        return torch.einsum("cgnhw,ng->cnhw", keys, self.base_weights[idx])

    def _gain(self) -> Tensor:
        return self.log_gain.exp()

    def gs_matrix(self) -> Tensor:
        """The learned GS-to-RS transform, 3x3 on pixel coordinates from the grid's centre."""
        return pose_matrix(self.gs_pose * self.pose_free, self.pose_radius)

    def _gs_view(self, pred: Tensor) -> tuple[Tensor, Tensor | None]:
        """GS predictions (C, G, H, W) of a video in RS coordinates as the GS camera sees them
        (sampled at S p) and the pixels where that needs no value from outside the grid (None:
        no pose learned). For residuals of an output video; the fit's GS term needs no warp."""
        if not self.learn_pose:
            return pred, None
        m = self.gs_matrix()
        return warp(pred, m), inside(m, self.H, self.W)

    def _rs_view(self, frames: Tensor) -> Tensor:
        """Frames (C, n, H, W) of the fields (GS coordinates) in RS coordinates: sampled at S^-1 q."""
        if not self.learn_pose:
            return frames
        if self.pose_is_shift:  # S is a translation by the pose's (dx, dy): S^-1 moves back by them
            shift = self.gs_pose[:2] * self.pose_free[:2]
            return warp_shift(frames, -shift[0], -shift[1])
        return warp(frames, torch.linalg.inv(self.gs_matrix()))

    def frames(self, idx: Tensor, static: Tensor | None = None) -> Tensor:
        """Video frames idx (C, n, H, W), before any hard GS anchoring (zero outside the mask).

        `static` may pass in the static image already evaluated for this step."""
        n = len(idx)
        if self.parts.static and static is None:
            static = self._static()
        if not self.parts.motion:
            v = static[:, None].expand(self.C, n, self.H, self.W)
        else:
            colour, alpha = self._dynamic_at(self._motion(idx), idx)
            v = colour if not self.parts.static else alpha * static[:, None] + (1 - alpha) * colour
        return v if self.mask is None else v * self.mask

    def _anchored(self, v_gs: Tensor) -> Tensor:
        """Hard anchoring of the GS-window frames (C, S, H, W) onto Lambda b_G."""
        target = self._gain()[:, None, None, None] * self.problem.b_gs
        windows = torch.arange(self.w_gs.shape[0], device=self.device)
        miss = target - self.gs_op.A_frames(v_gs, windows, self.gs_frames)
        if self.mask is not None:
            miss = miss * self.mask
        if self.gs_fit is not None:  # exact while GS exposures do not overlap in time
            miss = miss * self.gs_fit
        if self.gs_valid is not None:  # saturated GS pixels say nothing: left as the fields make them
            miss = miss * self.gs_valid
        return v_gs + torch.einsum("sg,cghw->cshw", self.anchor_p, miss)

    def _gs_window(self) -> Tensor:
        v = self.frames(self.gs_frames)
        return self._anchored(v) if self.settings.gs_anchor == "hard" else v

    def _video_frames(self, idx: Tensor, native: bool = False) -> Tensor:
        """Frames idx of the video as output, in RS coordinates (`native`: the fields' own, the GS
        camera's), with hard anchoring where it applies."""
        if not native and self.learn_pose:
            return self._rs_view(self.frames(idx))  # learn_pose: soft anchoring
        if self.settings.gs_anchor != "hard" or not self.parts.gs:
            return self.frames(idx)
        inside = torch.isin(idx, self.gs_frames)
        if not bool(inside.any()):
            return self.frames(idx)
        window = self._gs_window()
        out = self.frames(idx)
        out[:, inside] = window[:, torch.searchsorted(self.gs_frames, idx[inside])]
        return out

