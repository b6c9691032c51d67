"""The stages' configs: each number a stage decides by, its default, and the reason with the bench/
table that measured it (rngcam.recon.methods.stfm.stages; `--set stage.field=value` changes one)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from rngcam.errors import ConfigError


@dataclass(frozen=True)
class AutoPresetConfig:
    # mean layer misfit under which one translating layer explains the key frames: sineball 0.29 (64 px),
    # 0.39 (32 px); smoke 0.68, 0.60; real clips 0.72-1.0 (bench/stfm_motion.md)
    layer_misfit_max: float = 0.5

    def __post_init__(self):
        if not 0 < self.layer_misfit_max:
            raise ConfigError(f"stfm: auto_preset.layer_misfit_max must be > 0, got {self.layer_misfit_max!r}")


FLOOR_VIDEOS = ("blend", "interp")  # the GS-only videos the start floor can make (the baselines' functions)


@dataclass(frozen=True)
class StartFloorConfig:
    # the GS-only videos the fit must explain the RS image better than (bench/stfm_compare.md)
    candidates: tuple = FLOOR_VIDEOS

    def __post_init__(self):
        bad = [c for c in self.candidates if c not in FLOOR_VIDEOS]
        if bad or not self.candidates:
            raise ConfigError(f"stfm: start_floor.candidates must be blend and/or interp, got {self.candidates!r}")


@dataclass(frozen=True)
class LineRefitConfig:
    # a learned factor further than this from where the fit started makes another fit: past what the lab
    # family's +-0.5 % is learned as; the first fit learns a 2 % error as 1.78 % (bench/realistic.md, "a
    # search-started fit runs four half-lives of its step")
    refit_line_time: float = 0.01
    # later fits at most: each closes most of what the one before left (a 2 % error in three; bench/realistic.md)
    max_refits: int = 3
    # from a fit that ended unexplained, one later fit where its factor is this far off: another error moves
    # its line time ("together" capture, bench/realistic.md, "the line time learned on over later fits")
    refit_line_time_unexplained: float = 0.007

    def __post_init__(self):
        if not (self.refit_line_time > 0 and self.refit_line_time_unexplained > 0 and self.max_refits >= 0):
            raise ConfigError("stfm: line_refit's thresholds must be > 0 and max_refits >= 0")


@dataclass(frozen=True)
class EdgeRefitConfig:
    # the key rows' PSF scale at or below which the PSF is taken as measured too large (bench/realistic.md)
    max_scale: float = 0.99
    # the share by which the fitted edge must lower the best video's RS residual (bench/realistic.md)
    min_drop: float = 0.15
    # fits through a fitted edge after the first
    max_refits: int = 2

    def __post_init__(self):
        if not (0 < self.max_scale <= 1 and 0 <= self.min_drop < 1 and self.max_refits >= 0):
            raise ConfigError("stfm: psf_edge needs 0 < max_scale <= 1, 0 <= min_drop < 1, max_refits >= 0")


@dataclass(frozen=True)
class TrackRefitConfig:
    # the second run's turn penalty, of the search's: half the penalty kept the ball where the first lost
    # it (sineball lab seed 1: 1.43x -> 1.02x its noise level; bench/realistic.md, "a run left unexplained
    # is made again from a softer motion search")
    turn_scale: float = 0.5

    def __post_init__(self):
        if not 0 < self.turn_scale:
            raise ConfigError(f"stfm: track_refit.turn_scale must be > 0, got {self.turn_scale!r}")


@dataclass(frozen=True)
class FitConfig:
    """The fit's schedule for what it learns of the rig with its fields (the GS-to-RS pose and the RS line
    time) and for a search-started fit's least steps."""

    # The learned GS-to-RS pose's step (Adam, pixels of displacement at the grid's edge) per unit of the
    # fields' learning rate, decaying with it: a smaller ratio did not reach smoke's shift, a step that does
    # not decay cost sineball steps for nothing (bench/stfm_history.md); larger ones lost where there is no
    # shift (bench/realistic.md, "The learned shift's step size on sineball")
    pose_lr_ratio: float = 2.0
    # A fit that learns the pose from its start holds it for its first steps: while the fields are far from
    # the data, a shift along the scene's motion explains what they get wrong about its timing (smoke rises:
    # every ensemble member put a shift in y within its first steps, on captures with none, and kept it).
    # After the hold its step is pose_lr_after_hold times pose_lr_ratio, to reach a 1 px shift in the steps
    # left (bench/realistic.md, "the learned pose held while the fields settle"). A fit started from
    # another's pose neither holds nor speeds up.
    pose_hold_steps: int = 100
    pose_lr_after_hold: float = 3.0
    # A fit whose motion starts from the translation search (the prior preset) holds the learned line time
    # for its first steps: from the search's track the line time took up the track's timing, and the ball
    # came later and later (bench/realistic.md, "the motion search charges turns"). Held for a shorter time,
    # a capture still moved it the wrong way; held this long, it stays near the recorded figure
    # (bench/realistic.md, "a search-started fit holds its line time 600 steps"). A fit started from
    # another's line time or fields does not hold it.
    line_hold_steps_search: int = 600
    # The learned line time's step (Adam, frames of displacement at the last RS row) per unit of the fields'
    # learning rate: a smaller step learned too little of an error (bench/realistic.md, "the line time
    # learned on over later fits")
    line_lr_ratio: float = 32.0
    # After the hold the step is this many times line_lr_ratio: the same step at the hold's end as
    # line_lr_ratio at the end of a 300-step hold (the fields' step halves every 400 steps). x1 learned too
    # little of an error, x4 wandered on exact timing (bench/realistic.md, "a search-started fit holds its
    # line time 600 steps").
    line_lr_after_hold: float = 2.0
    # A search-started fit whose RS residual is within EXPLAINED_RATIO of its noise level runs this many
    # half-lives of its step before its stop tests may end it: its video still gains long after the residual
    # has gone flat (bench/realistic.md, "a search-started fit runs four half-lives of its step")
    search_fit_half_lives: float = 4.0

    def __post_init__(self):
        figures = (self.pose_lr_ratio, self.pose_lr_after_hold, self.line_lr_ratio, self.line_lr_after_hold,
                   self.search_fit_half_lives, self.pose_hold_steps, self.line_hold_steps_search)
        if not all(math.isfinite(v) and v >= 0 for v in figures):
            raise ConfigError("stfm: the fit stage's ratios, holds and half-lives must be finite and >= 0")


def fit_config(settings) -> FitConfig:
    """The fit stage's config of `settings` (its `stages["fit"]`, checked; the defaults elsewhere)."""
    return FitConfig(**((getattr(settings, "stages", None) or {}).get("fit") or {}))
