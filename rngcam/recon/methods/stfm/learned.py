"""What an STFM fit learns about the rig with its fields: each quantity one `Learned` object.

Every quantity says the same four things: its parameter (`parameter`, stepped by the fit's optimiser in
a group of its own where `learned`), its prior (where it starts and whether it is held while the fields
settle: `schedule`), how it enters the forward model (each class's apply methods: the gains scale the
GS data, the pose moves the frames between the cameras' coordinates, the line time stretches the RS
rows' exposure windows) and what it reports (`report`, `notes`). The line time is
rngcam.recon.methods.stfm.line_time.LineTime. A quantity measured before the fit (the PSF's scale,
self-calibration's gains and pose: rngcam.recon.methods.selfcal) reaches the fit as its problem and
start, and the fit's report counts from it. The verdicts read these reports (rngcam.recon.misfit).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from rngcam.errors import ConfigError
from rngcam.recon.methods.selfcal import describe, inside, pose_matrix, similarity, warp, warp_translate


def held_schedule(hold_steps: int, ratio: float, after_hold: float) -> dict:
    """An optimiser group's schedule: held (no step) for `hold_steps`, then stepped at `ratio` x
    `after_hold` of the fields' learning rate (the fields' step has decayed meanwhile); `ratio` without
    a hold."""
    return {"hold_steps": hold_steps, "lr_ratio": ratio * (after_hold if hold_steps else 1.0)}


class Learned:
    """One quantity the fit learns with its fields. Subclasses set `name`, `parameter` and `learned`."""

    name = ""
    parameter: nn.Parameter
    learned = False
    inherited = False  # started from another fit's value (a finer level, a later fit)

    def schedule(self) -> dict:
        """The optimiser group's {"hold_steps", "lr_ratio"} (ratio to the fields' learning rate)."""
        raise NotImplementedError

    def report(self, value) -> dict | None:
        """What the outputs say of `value` (the averaged parameter's reading; None: not learned)."""
        return None

    def transfer(self, other: Learned, scale: float) -> None:
        """Start from `other`'s value (the same quantity of a coarser level), `scale`d to this grid."""
        with torch.no_grad():
            self.parameter.copy_(other.parameter.detach().to(self.parameter) * scale)
        self.inherited = True


class Gains(Learned):
    """The GS/RS colour gains Lambda (log-parametrised, one per channel): the GS term compares the frames
    with Lambda b_G, and a base video is moved onto the RS scale by them. Prior: the bundle's white
    balance (1 without one)."""

    name = "gains"

    def __init__(self, white_balance: Tensor | None, channels: int, lr_ratio: float, learned: bool, device):
        start = torch.ones(channels, device=device) if white_balance is None else white_balance.to(device).float()
        if not torch.all(start > 0):
            raise ConfigError(f"white balance gains must be > 0, got {start.tolist()}")
        self.parameter = nn.Parameter(start.log())
        self.lr_ratio, self.learned = lr_ratio, learned

    def value(self) -> Tensor:
        return self.parameter.exp()

    def schedule(self) -> dict:
        return {"lr_ratio": self.lr_ratio}


class Pose(Learned):
    """The GS-to-RS transform S (the GS camera's pixel p sees the scene at S p), `pose_matrix`'s four
    parameters. The fields live in the GS camera's coordinates, so that the GS term does not depend on S
    (else the fields and S trade a shift along a flat valley that only the RS term tilts); the RS term
    and the output video see the frames in RS coordinates, sampled at S^-1 q (`rs_view`). Prior: the
    transform self-calibration left (identity here), held while the fields settle (FitConfig)."""

    name = "pose"

    def __init__(self, height: int, width: int, device):
        self.parameter = nn.Parameter(torch.zeros(4, device=device))
        self.free = torch.ones(4, device=device)  # 0: that value held at zero
        self.radius = max(height, width) / 2
        self.is_shift = False  # rotation and scale held at zero (learn_geometry "shift")
        self.height, self.width = height, width
        self.config = None

    def enable(self, mode: str, learned: bool, config) -> None:
        """Learn the pose (`learned`) as `mode` ("shift": rotation and scale held at zero), on the fit
        stage's schedule `config` (FitConfig)."""
        if mode == "shift":  # rotation and scale held at zero (no gradient reaches them)
            self.free[2:] = 0
            self.is_shift = True
        self.learned, self.config = learned, config

    def schedule(self) -> dict:
        """Held while a fit that learns the pose from its start settles its fields, then stepped faster;
        one started from another fit's pose neither."""
        f = self.config
        return held_schedule(0 if self.inherited else f.pose_hold_steps, f.pose_lr_ratio, f.pose_lr_after_hold)

    def matrix(self) -> Tensor:
        """The learned GS-to-RS transform, 3x3 on pixel coordinates from the grid's centre."""
        return pose_matrix(self.parameter * self.free, self.radius)

    def gs_view(self, pred: Tensor) -> tuple[Tensor, Tensor | None]:
        """GS predictions (C, G, H, W) of a video in RS coordinates as the GS camera sees them
        (sampled at S p) and the pixels where that needs no value from outside the grid (None:
        no pose learned). For residuals of an output video; the fit's GS term needs no warp."""
        if not self.learned:
            return pred, None
        m = self.matrix()
        return warp(pred, m), inside(m, self.height, self.width)

    def rs_view(self, frames: Tensor) -> Tensor:
        """Frames (C, n, H, W) of the fields (GS coordinates) in RS coordinates: sampled at S^-1 q."""
        if not self.learned:
            return frames
        if self.is_shift:  # S is a translation by the pose's (dx, dy): S^-1 moves back by them
            return warp_translate(frames, -(self.parameter[:2] * self.free[:2]))
        return warp(frames, torch.linalg.inv(self.matrix()))

    def reading(self) -> Tensor | None:
        """The pose as learned (4,), None where the fit does not learn it."""
        return (self.parameter * self.free).detach().clone() if self.learned else None

    def report(self, value: Tensor | None, selfcal: dict | None = None) -> dict | None:
        """geometry_report of `value` (a reading), counted from the transform self-calibration applied."""
        return geometry_report(value, self.radius, selfcal)


def geometry_report(pose: Tensor | None, radius: float, selfcal: dict | None) -> dict | None:
    """{"start" (the transform the GS frames were taken to RS coordinates by before the fit),
    "learned" (the fit's on top of it), "end" (both: what the rig has)} as shift / rotation / scale."""
    if pose is None:
        return None
    start = similarity()
    if selfcal and selfcal.get("applied") and "transform_not_applied" not in selfcal:
        r = selfcal["refined"]
        start = similarity(*r["shift_px"], np.radians(r["rotation_deg"]), r["scale"])
    learned = pose_matrix(pose.double().cpu(), radius).numpy()
    return {"start": describe(start), "learned": describe(learned), "end": describe(learned @ start)}


def geometry_lines(geometry: dict | None, steps: int) -> list[str]:
    """The note on the learned GS-to-RS transform (none before the first step)."""
    if geometry is None or steps == 0:
        return []
    e = geometry["end"]
    return [f"GS-to-RS transform learned with the fields: shift ({e['shift_px'][0]:+.3f}, {e['shift_px'][1]:+.3f}) px, "
            f"rotation {e['rotation_deg']:+.3f} deg, scale {e['scale']:.4f}"]
