"""The stages' configs: each number a stage decides by, its default, and the reason with the bench/
table that measured it (rngcam.recon.methods.stfm.stages; `--set stage.field=value` changes one)."""

from __future__ import annotations

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


@dataclass(frozen=True)
class StartFloorConfig:
    # the GS-only videos the fit must explain the RS image better than (bench/stfm_compare.md)
    candidates: tuple = ("blend", "interp")

    def __post_init__(self):
        bad = [c for c in self.candidates if c not in ("blend", "interp")]
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
