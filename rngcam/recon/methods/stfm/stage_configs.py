"""The stages' configs: each number a stage decides by, its default, and the reason with the bench/
table that measured it (rngcam.recon.methods.stfm.stages; `--set stage.field=value` changes one)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from rngcam.errors import ConfigError
from rngcam.recon.misfit import EXPLAINED_RATIO


@dataclass(frozen=True)
class AutoPresetConfig:
    # largest layer misfit under which one translating layer explains the key frames: sineball 0.25-0.35
    # (64 px, grid, fine and lab, seeds 0-2); smoke 0.77-0.87; the packaged clip 1.15-1.16
    # (bench/untuned.md, "the layer test's worst key frame"; the means were set on in bench/stfm_motion.md)
    layer_misfit_max: float = 0.5
    # key frames are binned by a whole factor to no less than this longer side first: the scale the misfits
    # above were measured at (32 and 64 px), and a test in a second at any grid (bench/stfm_motion.md)
    layer_test_side: int = 64

    def __post_init__(self):
        if not 0 < self.layer_misfit_max:
            raise ConfigError(f"stfm: auto_preset.layer_misfit_max must be > 0, got {self.layer_misfit_max!r}")
        if self.layer_test_side < 2:
            raise ConfigError(f"stfm: auto_preset.layer_test_side must be >= 2, got {self.layer_test_side!r}")


FLOOR_VIDEOS = ("blend", "interp", "rife")  # the GS-only videos the check can make (RIFE where its weights are)


@dataclass(frozen=True)
class HoldOutConfig:
    # the share of RS rows the fields do not fit until the check has judged (the motion search reads them; a
    # kept fit then fits them in: start_floor.polish), in blocks one exposure long: 0.05 told the fit from the
    # GS-only videos by 4-32 noise deviations (bench/untuned.md, "the self-check"); held out to the end it cost
    # sineball 0.19-0.83 dB (bench/realistic.md, "the held-out rows"); 0: none held out
    fraction: float = 0.05
    seed: int = 0  # where the blocks fall (Problem.with_holdout)

    def __post_init__(self):
        if not 0 <= self.fraction <= 0.3:
            raise ConfigError(f"stfm: hold_out.fraction must be in [0, 0.3], got {self.fraction!r}")


@dataclass(frozen=True)
class StartFloorConfig:
    # the GS-only videos the fit is checked against; the best on the judged rows is the reference
    candidates: tuple = FLOOR_VIDEOS
    # the fit gives way to the reference only where it explains the held-out rows worse by this many standard
    # deviations of the noise's share of the difference (two: one false alarm in 44 where both are as good)
    significance: float = 2.0
    # once the check has kept the fit, it fits the held-out rows too, to its next stop: held out to the end
    # they cost sineball 0.19-0.83 dB (bench/realistic.md, "the held-out rows")
    polish: bool = True

    def __post_init__(self):
        bad = [c for c in self.candidates if c not in FLOOR_VIDEOS]
        if bad or not self.candidates:
            raise ConfigError(f"stfm: start_floor.candidates must be of {', '.join(FLOOR_VIDEOS)}, "
                              f"got {self.candidates!r}")
        if not self.significance >= 0:
            raise ConfigError(f"stfm: start_floor.significance must be >= 0, got {self.significance!r}")


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
    # the second run's turn penalty, of the search's: half the penalty kept the ball where the first run lost
    # it, and that run ended near its noise level (bench/realistic.md, "a run left unexplained is made again
    # from a softer motion search")
    turn_scale: float = 0.5

    def __post_init__(self):
        if not 0 < self.turn_scale:
            raise ConfigError(f"stfm: track_refit.turn_scale must be > 0, got {self.turn_scale!r}")


class _Checked:
    """A config assembled from parts: each part's `_check` runs on the whole (FitConfig's parts)."""

    def __post_init__(self):
        for cls in reversed(type(self).__mro__):
            check = vars(cls).get("_check")
            if check is not None:
                check(self)


def _finite(config, names: tuple[str, ...], low: float = 0.0) -> bool:
    return all(math.isfinite(getattr(config, n)) and getattr(config, n) >= low for n in names)


@dataclass(frozen=True)
class StopConfig(_Checked):
    """When a fit's stop tests run and what they call explained (stopping.py)."""

    # A fit that ends at this many times its noise level or more is not explained: the PSF-edge, row-gain and
    # track stages fit again from it, another error (a PSF at another scale) moves its line time, so one later
    # line fit from it at most (line_refit), and it is stopped where it stalls, not run on (bench/realistic.md,
    # "a run left unexplained is made again from a softer motion search")
    explained_ratio: float = EXPLAINED_RATIO  # its reason: rngcam.recon.misfit
    # Steps between stop tests (each makes the whole video: one full RS forward) up to noise_check_frames
    # frames, one more interval for each further noise_check_frames (bench/convergence.md, "the large grids'
    # budget spent where it pays")
    noise_check_steps: int = 20
    noise_check_frames: int = 80

    def _check(self):
        if not (self.explained_ratio >= 1 and self.noise_check_steps >= 1 and self.noise_check_frames >= 1):
            raise ConfigError("stfm: fit.explained_ratio must be >= 1, noise_check_steps and noise_check_frames >= 1")


@dataclass(frozen=True)
class RefineConfig(_Checked):
    """The ensemble's refinement fit (and a finer level's fit on the level below): what it starts from
    is already good (ensemble.py, multilevel.py); and the ensemble's deadline check."""

    # Its learning rate, of the members': it moves an already good video (bench/convergence.md, "the half
    # grid first again": more steps at 4x the learning rate did not help)
    refine_lr_ratio: float = 0.25
    # Its stall test looks back this many passes over the rows (unless stall_passes is set): what it gains,
    # it gains in its first steps (bench/convergence.md, "log rows and the refinement's stall window")
    refine_stall_passes: int = 5
    # Fits of one base under a deadline: how often (the first fit's steps) the time they still need is checked
    # (bench/demo.md, "the prior preset's two fits; the demo's budget lets the second go")
    afford_check_steps: int = 100

    def _check(self):
        if not (_finite(self, ("refine_lr_ratio",)) and self.refine_lr_ratio > 0 and self.refine_stall_passes >= 1
                and self.afford_check_steps >= 1):
            raise ConfigError("stfm: fit.refine_lr_ratio must be > 0, refine_stall_passes and afford_check_steps >= 1")


@dataclass(frozen=True)
class MultilevelConfig(_Checked):
    """Coarse to fine (multilevel.py): the levels' steps and budget shares, and where a small grid
    still starts on its half grid."""

    # A coarse level that never meets its stop test ends here (bench/large_grids.md, "Tried after the issue
    # was blocked: a lower cap on the coarse levels")
    max_level_steps: int = 3000
    # Under a time budget a coarse level of a base-video model (fast) may spend this share of what is left
    # when it starts (the full level gets the rest): its coarse steps are cheaper and carry most of the result,
    # and this share scored best on the paper grid. A model that carries its fields (prior) keeps
    # CoarseToFine's: its full level carries the detail, and a larger share cost it PSNR and the ball's place
    # (bench/convergence.md, "the large grids' budget spent where it pays")
    level_share: float = 0.45
    # ... and on the half-grid-first path (below 96 px) this share: its full level is one short refinement,
    # so level_share cut the half grid short under a budget longer than its own stop (bench/convergence.md,
    # "the half grid first again")
    half_grid_level_share: float = 0.85
    # Below 96 px, where the default levels are one, a base-video model (fast) still starts on the half grid
    # when that keeps this many pixels a side: its ensemble there, with bases from the full grid's frames,
    # then one fit on the full grid: a fraction of the wall time for the same PSNR (bench/convergence.md,
    # "the half grid first again"; bench/realistic.md, "the lab-to-fine gap and the learned shift"). A model
    # that carries its fields (prior) keeps one level.
    base_min_side: int = 32

    def _check(self):
        shares = (self.level_share, self.half_grid_level_share)
        if not (all(0 < s <= 1 for s in shares) and self.max_level_steps >= 1 and self.base_min_side >= 1):
            raise ConfigError("stfm: fit's level shares must be in (0, 1], max_level_steps and base_min_side >= 1")


@dataclass(frozen=True)
class MotionSearchConfig(_Checked):
    """The prior preset's motion start (motion_search.py): which shifts it tries and what its
    Viterbi pass charges."""

    # Shifts up to this fraction of the image side each way: every integer shift a layer can take and stay
    # partly in the frame (bench/stfm_motion.md, "What the prior preset is")
    search_reach: float = 0.6
    # About this many candidate positions per axis: 1 px steps up to about 107 px images, coarser above
    # (the search's cost is one RS forward per candidate)
    search_points: int = 64
    # L1 penalty per pixel of shift change between frames (normalised costs; bench/realistic.md, "the motion
    # search charges turns")
    search_smooth: float = 1e-3
    # L1 penalty per px/frame of change in velocity at a 64 px side (normalised costs): the RS rows often
    # cannot tell a smooth path from a detour between key frames (bench/realistic.md, "the motion search
    # charges turns")
    search_turn: float = 0.1
    # Fastest motion searched: this share of the image side per frame, per axis (bench/realistic.md, "the
    # motion search charges turns")
    search_speed: float = 0.125
    # A key frame's object mask: 1 where it differs from the key frames' median by this share of the median's
    # mean (the layer the search moves; not tuned alone: the search as a whole is in bench/stfm_motion.md,
    # "What the prior preset is")
    layer_change: float = 0.1

    def _check(self):
        names = ("search_reach", "search_smooth", "search_turn", "search_speed", "layer_change")
        if not (_finite(self, names) and self.search_reach > 0 and self.search_points >= 2
                and self.search_speed > 0 and self.layer_change > 0):
            raise ConfigError("stfm: fit's search_* and layer_change must be finite and > 0 (search_points >= 2)")


@dataclass(frozen=True)
class ComponentsConfig(_Checked):
    """Which parts a scene needs (components.py): a dark background needs no static field, a static
    scene no motion. Detection thresholds on the data's own noise."""

    # the background (the GS frames' median) is dark below this share of the GS frames' peak
    dark_fraction: float = 0.02
    # a change beyond this many noise sigmas is real (the RS residual of a static scene: within half as many
    # of its own noise estimate)
    static_noise_factor: float = 5.0
    # ... plus this share of the signal (model and calibration slack)
    static_relative_tol: float = 0.002
    # the share of a GS frame's pixels allowed to change beyond noise in a static scene
    static_outlier_fraction: float = 1e-3

    def _check(self):
        names = ("dark_fraction", "static_noise_factor", "static_relative_tol", "static_outlier_fraction")
        if not _finite(self, names):
            raise ConfigError("stfm: fit's dark_fraction and static_* thresholds must be finite and >= 0")


@dataclass(frozen=True)
class InitConfig(_Checked):
    """How a fit's fields start from the GS frames before the fit (init.py, init="gs")."""

    # Adam's step for the fits to the key frames, the flows and the search's track: a set-up fit, not tuned
    # alone (its seconds are in bench/convergence.md, "the large grids' budget spent where it pays")
    init_lr: float = 0.02
    # Weight of the alpha target against the colour target in those fits
    init_alpha_weight: float = 0.1
    # Frames a step of the motion field's fit to the key-frame flows; the search's track (one that turns
    # round) takes init_search_step_factor times the steps with init_search_frames frames a step
    init_frames_per_step: int = 4
    init_search_frames: int = 8
    init_search_step_factor: int = 3

    def _check(self):
        counts = (self.init_frames_per_step, self.init_search_frames, self.init_search_step_factor)
        if not (_finite(self, ("init_lr", "init_alpha_weight")) and self.init_lr > 0 and min(counts) >= 1):
            raise ConfigError("stfm: fit.init_* must be > 0 (frames and step factors whole numbers >= 1)")


@dataclass(frozen=True)
class EvaluationConfig(_Checked):
    """Where a fit decodes its fields (grid.FitGrid): fewer points than pixels where the field is smooth."""

    # A translation is the motion field's mean over this many points per axis of the frame (at most), not
    # over every pixel: the same family of motions for a fraction of the field's evaluations
    # (bench/convergence.md, "the prior preset's translation averaged over 16 x 16 points")
    translation_mean_points: int = 16
    # A motion field is decoded on knots this many pixels apart and interpolated bilinearly between them:
    # its finest planes have knots 4 px apart, so a quarter of the decoder's points cut a fast step's time
    # and not its result (bench/convergence.md, "the fast preset's motion on knots")
    motion_knot_px: float = 2.0
    # The prior preset's canonical image is decoded on knots this many pixels apart, the pixel centres on
    # them (1 / this a whole number), and moved by bilinear interpolation (bench/convergence.md, "the prior
    # preset decodes its canonical image once a step")
    canonical_knot_px: float = 0.5
    # The fields' step decays by half every lr_half_life_steps down to this share of its start
    lr_floor_share: float = 0.05

    def _check(self):
        inverse = 1 / self.canonical_knot_px if self.canonical_knot_px > 0 else 0.5
        if not (self.translation_mean_points >= 1 and self.motion_knot_px > 0 and 0 < self.canonical_knot_px <= 1
                and float(inverse).is_integer() and 0 < self.lr_floor_share <= 1):
            raise ConfigError("stfm: fit.translation_mean_points >= 1, motion_knot_px > 0, canonical_knot_px in (0, 1] "
                              "with 1 / it whole, 0 < lr_floor_share <= 1")


@dataclass(frozen=True)
class FitConfig(EvaluationConfig, InitConfig, ComponentsConfig, MotionSearchConfig, MultilevelConfig, RefineConfig,
                StopConfig):
    """The fit stage's numbers: its schedule for what it learns of the rig with its fields (the GS-to-RS
    pose and the RS line time), a search-started fit's least steps and the GS initialisation's steps, and
    its parts' (StopConfig, RefineConfig, MultilevelConfig, MotionSearchConfig, ComponentsConfig), all set
    as `--set fit.field=value`."""

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
    # Steps of the fit to the GS frames alone that initialises the fields (init="gs"): the key frames' own
    # detail before the RS term joins (a set-up cost, not tuned alone; its seconds are in bench/convergence.md,
    # "the large grids' budget spent where it pays")
    init_steps: int = 100

    def _check(self):
        figures = (self.pose_lr_ratio, self.pose_lr_after_hold, self.line_lr_ratio, self.line_lr_after_hold,
                   self.search_fit_half_lives, self.pose_hold_steps, self.line_hold_steps_search, self.init_steps)
        if not all(math.isfinite(v) and v >= 0 for v in figures):
            raise ConfigError("stfm: the fit stage's ratios, holds and half-lives must be finite and >= 0")


def fit_config(settings) -> FitConfig:
    """The fit stage's config of `settings` (its `stages["fit"]`, checked; the defaults elsewhere)."""
    return FitConfig(**((getattr(settings, "stages", None) or {}).get("fit") or {}))
