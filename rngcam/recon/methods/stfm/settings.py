"""STFM settings and the settings as resolved against a preset (the presets themselves: presets.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import torch

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm.presets import (  # noqa: F401 (the presets' windows, named here too)
    PRIOR_STALL_PASSES,
    SMALL_STALL_PASSES,
    STALL_PASSES,
    TRANSLATION_TV_SHARE,
)
from rngcam.recon.methods.stfm.presets import preset_table as _preset
from rngcam.recon.methods.stfm.stage_configs import FitConfig
from rngcam.recon.options import setting

PRESETS = ("paper", "fast", "prior", "auto")  # auto: prior or fast per scene (rngcam.recon.methods.stfm.auto)
# The fit stage's defaults under the names the package exports (a run sets them with `--set fit.init_steps=...`;
# stage_configs.FitConfig holds each one's reason)
INIT_STEPS = FitConfig.init_steps
NOISE_CHECK_STEPS = FitConfig.noise_check_steps
EXPLAINED_RATIO = FitConfig.explained_ratio
REFINE_LR_RATIO = FitConfig.refine_lr_ratio
REFINE_STALL_PASSES = FitConfig.refine_stall_passes
MIN_FLOW_SIZE_PX = 16  # below this the motion initialisation from optical flow is skipped
# A step holds one chunk of frames' autograd graph at a time. Small grids take more frames per chunk:
# a step's RS frames then fit in one graph, evaluated once instead of a pass without a graph and a pass
# with one (bench/convergence.md); large grids keep 4 frames. 32 frames at 64 px: the prior preset's
# half-frames (a step's rows touch about 21 with the GS window's) fit too (bench/step_ops.md).
CHUNK_POINTS = 131_072
MIN_FRAME_CHUNK = 4
# On a GPU larger graphs pay: at the paper grid 32 frames a graph (2.5 M points) ran more steps than 4
# in the same time, 128 frames no more (bench/large_grids.md, "The third GPU session"). A graph saves
# GRAPH_BYTES_PER_POINT a point (tests/test_memory.py): never more than an eighth of the card.
GPU_CHUNK_POINTS = 2_500_000
GRAPH_BYTES_PER_POINT = 1_200
GPU_GRAPH_SHARE = 8  # ... a graph takes at most 1 / this of the card's memory
# What learn_geometry learns of the GS-to-RS transform. "shift" by default: rotation and scale
# learned alongside drifted where the truth had none (bench/realistic.md, "the GS-to-RS shift learned
# with the fields"), as a scale trades against the PSF's magnification.
GEOMETRY_MODES = ("off", "shift", "similarity")
LINE_TIME_MODES = ("off", "on", "auto")
# The motion of the dynamic layer: a field over (x, y, t), or its mean over the frame, one translation
# per frame (the prior preset's: one rigid layer; a field varying across the object tore the ball).
MOTION_MODELS = ("field", "translation")
MAX_SUBFRAMES = 8  # subframes: more would multiply the time and memory of a fit for a blur already resolved
MAX_FITS = 4  # fits: each one more costs a whole fit's time (side by side where the run has the threads)


@dataclass
class STFMSettings:
    """User settings; None means "the preset's value"."""

    preset: str = "fast"
    beta: float | None = setting(None, "weight of the motion field's change along time relative to along "
                                       "x and y, inside the motion TV", unit="relative", sweep=True)
    tau: float | None = setting(None, "weight of the motion field's TV against the data terms",
                                unit="relative", sweep=True)
    psi: float = setting(1.0, "RS data weight relative to GS (each term scaled by its operator's norm)",
                         unit="relative", sweep=True)
    components: str = setting("auto", "leave out the fields the scene does not need (auto) or keep all",
                              choices=("auto", "all"))
    no_static: bool = setting(False, "no static background field (and no alpha matte)")
    no_motion_reg: bool = setting(False, "no TV on the motion field")
    no_rs: bool = setting(False, "leave the RS measurement out of the fit")
    no_gs: bool = setting(False, "leave the GS frames out of the fit")
    gs_anchor: str = setting("soft", "GS frames as a loss term (soft) or a projection onto them (hard)",
                             choices=("soft", "hard"))
    rows_per_step: int | None = None
    tv_frames_per_step: int = 2
    frame_chunk: int | None = None  # frames evaluated with one autograd graph (None: chunk_frames(H, W))
    seed: int = 0
    lr: float | None = None
    lr_half_life_steps: float | None = None  # exponential LR decay (None: preset's; inf: none)
    init: str | None = None  # "gs" (fit fields to the GS frames first) or "random"
    gs_windows_per_step: int | None = None  # GS frames per step (soft anchoring; 0: all)
    dynamic_time: bool | None = None  # 3-D F_D (with a base: F_D(x, y, t), the base moved), not F_D(x + u_x, y + u_y)
    dynamic_base: str | None = setting(
        None, "the GS-only start the dynamic field corrects: video (rife, else interp), rife, interp, keys "
              "(key frames warped by RIFE's flows, else DIS's), keys_rife, keys_interp, video_hdv3 or keys_hdv3 "
              "(RIFE HDv3 instead of 4.x), blend or none; a comma-separated list averages one fit per base; "
              "ensemble = video,keys,video_hdv3,keys_hdv3", cli="base")
    time_smoothness: float | None = None  # weight of the time planes' roughness (plane fields)
    matte_l1: float | None = setting(None, "weight of an L1 penalty on the canonical dynamic image's matte "
                                           "(1 - alpha; 2-D dynamic field only): the moving layer covers no "
                                           "more than the data need", unit="relative", sweep=True)
    stop_at_noise: bool | None = setting(None, "stop once the RS residual reaches the noise level estimated "
                                               "from the RS image, or stalls (falls by less than 2 % over 15 passes "
                                               "over the RS rows in the fast preset, 0.1 % over 45 in prior)")
    stall_drop: float | None = None  # ... or once it fell less than this fraction over stall_passes (0: off)
    stall_passes: int | None = None  # passes over the RS rows the stall test looks back
    ema_decay: float | None = None  # outputs use an exponential moving average of the weights (0: off)
    refine: bool | None = None  # ensemble: one more fit on the members' average once they have stopped
    motion_init: str | None = None  # 2-D dynamic field: "flow" (key-frame optical flow) or "search" (motion_search)
    motion_model: str | None = setting(
        None, "the dynamic layer's motion: a field over x, y and t, or one translation per frame (a rigid layer; "
              "the prior preset's, whose scenes one translating layer explains); default: the preset's",
        choices=MOTION_MODELS, shown_default="the preset's")
    subframes: int | None = setting(
        None, "fit each output frame as this many shorter frames and average them into it: an RS row's exposure "
              "begins and ends inside frames, and a fast object moves within one (the prior preset: 2; fast and "
              "paper: 1, the output's frames)", unit="frames", shown_default="the preset's")
    fits: int | None = setting(
        None, "independent fits of one dynamic base from consecutive seeds, stepped side by side and their videos "
              "averaged: each keeps its own error where the data do not pin the video, and the errors average "
              f"out (the prior preset: 2; fast and paper: 1; at most {MAX_FITS}; one a level where a run goes "
              "coarse to fine)", unit="fits",
        shown_default="the preset's")
    coarse_to_fine: bool = setting(True, "reconstruct coarser grids first (1/2 from 96 px, from 64 px for the fast "
                                         "preset; 1/4 too from 192 px), each starting the next "
                                         "(else one level at the full grid)")
    self_calibrate: str = setting(
        "off", "refine the calibration from the RS rows exposed with the GS frames before the fit "
                 "(rngcam.recon.methods.selfcal): gains (GS/RS colour gains), all (and the GS-to-RS shift, rotation "
                 "and scale, the PSF's background and the GS vignetting where the data pin them), or off",
        choices=("off", "gains", "all"))
    self_calibrate_psf_scale: bool = setting(
        True, "with self_calibrate, also search the PSF's magnification (0.9-1.1) on those rows; applied where it "
              "lowers their residual by 3 % or more (else reported)")
    psf_edge: bool = setting(
        True, "with self_calibrate, where the key rows find the PSF measured too large (scale <= 0.99) and the fit "
              "ends above 1.15x its noise level: fit the edge the PSF lost off the sensor to the fit's video, "
              "fit again through that PSF and keep the fit that explains the RS image better")
    line_refit: bool = setting(
        True, "where the fit learns the RS line time (learn_line_time) and ends with it more than 1 % off where "
              "it started: fit again from the start at the learned line time, learning it on from there (up to "
              "three more fits; one, from 0.7 %, after a fit that ends at 1.15x its noise level or more), and "
              "keep the fit that explains the RS image best")
    row_gain_refit: bool = setting(
        True, "with self_calibrate, where the key rows find the PSF measured too large and the run (or a later fit "
              "through a fitted PSF edge or line time) ends at 1.15x its noise level or more: make it again with a "
              "motion search that scores each RS row after its own gain (a PSF that lost its edge predicts the "
              "rows' light short by varying amounts), and keep the one that explains the RS image better")
    track_refit: bool = setting(
        True, "where the motion starts from the translation search (the prior preset) and the run ends at 1.15x "
              "its noise level or more (and row_gain_refit does not apply): make it again from a search with half "
              "the turn penalty, and keep the one that explains the RS image better")
    preset_refit: bool = setting(
        True, "where the prior preset's run gives way at the self-check (a GS-only video explains the RS rows, held "
              "out and fitted, clearly better than the fit): make the run again with the fast preset, and keep the "
              "one whose fit explains the RS image better")
    learn_geometry: str = setting(
        "off", "learn the GS-to-RS transform with the fields: its shift, or shift, rotation and scale "
               "(similarity); needs both cameras and soft GS anchoring", choices=GEOMETRY_MODES)
    learn_line_time: str = setting(
        "off", "learn a factor on the RS line time with the fields (the recorded one is a rough figure on "
               "real cameras): on, off, or auto (on with the prior preset, one moving layer whose motion times "
               "the rows; off with fast, where spread motion let it drift); needs both cameras, soft GS "
               "anchoring and the bundle's RS timing", choices=LINE_TIME_MODES)
    stages: dict | None = field(default=None, metadata={"internal": True})  # --set / --recipe: {stage: {field: value}}
    start_floor: bool = setting(False, "output the best GS-only video (cross-fade or flow interpolation) "
                                      "instead of the fit when the fit's RS residual is not below its own")

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ConfigError(f"stfm: unknown preset {self.preset!r} (choose from {', '.join(PRESETS)})")
        if self.components not in ("auto", "all"):
            raise ConfigError(f"stfm: components must be 'auto' or 'all', got {self.components!r}")
        if self.gs_anchor not in ("soft", "hard"):
            raise ConfigError(f"stfm: gs_anchor must be 'soft' or 'hard', got {self.gs_anchor!r}")
        if self.self_calibrate not in ("off", "gains", "all"):
            raise ConfigError(f"stfm: self_calibrate must be off, gains or all, got {self.self_calibrate!r}")
        if self.learn_geometry not in GEOMETRY_MODES:
            raise ConfigError(f"stfm: learn_geometry must be one of {', '.join(GEOMETRY_MODES)}, "
                              f"got {self.learn_geometry!r}")
        if self.learn_line_time not in LINE_TIME_MODES:
            raise ConfigError(f"stfm: learn_line_time must be one of {', '.join(LINE_TIME_MODES)}, "
                              f"got {self.learn_line_time!r}")
        if self.motion_model not in (None, *MOTION_MODELS):
            raise ConfigError(f"stfm: motion_model must be one of {', '.join(MOTION_MODELS)}, "
                              f"got {self.motion_model!r}")
        if self.motion_init not in (None, "flow", "search"):
            raise ConfigError(f"stfm: motion_init must be 'flow' or 'search', got {self.motion_init!r}")
        if self.init not in (None, "gs", "random"):
            raise ConfigError(f"stfm: init must be 'gs' or 'random', got {self.init!r}")
        if self.dynamic_base is not None:
            bases = _base_list(self.dynamic_base)
            bad = [b for b in bases if b not in ALL_BASES]
            if bad or len(set(bases)) != len(bases):
                raise ConfigError(f"stfm: dynamic_base must be one of {', '.join(ALL_BASES)}, a comma-separated list "
                                  f"of distinct ones, or 'ensemble' ({ENSEMBLE_BASES}); got {self.dynamic_base!r}")
        steps = self.subframes
        if steps is not None and not (isinstance(steps, int) and 1 <= steps <= MAX_SUBFRAMES):
            raise ConfigError(f"stfm: subframes must be a whole number from 1 to {MAX_SUBFRAMES}, got {steps!r}")
        if self.fits is not None and not (isinstance(self.fits, int) and 1 <= self.fits <= MAX_FITS):
            raise ConfigError(f"stfm: fits must be a whole number from 1 to {MAX_FITS}, got {self.fits!r}")
        if self.stall_drop is not None and not 0 <= self.stall_drop < 1:
            raise ConfigError(f"stfm: stall_drop must be in [0, 1), got {self.stall_drop!r}")
        if self.stall_passes is not None and self.stall_passes < 1:
            raise ConfigError(f"stfm: stall_passes must be >= 1, got {self.stall_passes!r}")
        if self.ema_decay is not None and not 0 <= self.ema_decay < 1:
            raise ConfigError(f"stfm: ema_decay must be in [0, 1), got {self.ema_decay!r}")
        for name in ("beta", "tau", "psi", "lr", "matte_l1"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"stfm: {name} must be a finite number >= 0, got {value!r}")
        if self.rows_per_step is not None and self.rows_per_step < 1:
            raise ConfigError(f"stfm: rows_per_step must be >= 1, got {self.rows_per_step}")
        if self.gs_windows_per_step is not None and self.gs_windows_per_step < 0:
            raise ConfigError(f"stfm: gs_windows_per_step must be >= 0, got {self.gs_windows_per_step}")
        if self.stages is not None and not isinstance(self.stages, dict):
            raise ConfigError(f"stfm: stages must map stage names to their settings, got {self.stages!r}")
        if self.tv_frames_per_step < 1 or (self.frame_chunk is not None and self.frame_chunk < 1):
            raise ConfigError("tv_frames_per_step and frame_chunk must be >= 1")


BASE_VIDEOS = ("video", "rife", "interp")  # "video": rife when its weights are installed, else interp
KEY_WARPS = ("keys", "keys_rife", "keys_interp")  # "keys": RIFE's flows when installed, else DIS flows
HDV3_SUFFIX = "_hdv3"  # "video_hdv3", "keys_hdv3": the same bases from RIFE HDv3 instead of the default RIFE 4.x
ALL_BASES = (*BASE_VIDEOS, *KEY_WARPS, "blend", "none", "video" + HDV3_SUFFIX, "keys" + HDV3_SUFFIX)
# dynamic_base="ensemble": one fit on each of these bases, averaged (STFMEnsemble). Their errors
# in what the RS image cannot see differ, so the average is closer to the truth than any one of them.
# One pair per RIFE model (4.x and HDv3): the two models err differently, so the four average more away
# than "video,keys"; a member on DIS flows (keys_interp) cost the clips (bench/stfm_motion.md,
# bench/stfm_compare.md)
ENSEMBLE_BASES = "video,keys,video_hdv3,keys_hdv3"


# ----------------------------------------------------------------------------- the method


@dataclass
class _Resolved:
    """Settings after the preset has filled the blanks (stored in outputs)."""

    settings: STFMSettings
    beta: float
    tau: float
    lr: float
    lr_half_life_steps: float
    rows_per_step: int
    init: str
    dynamic_time: bool
    dynamic_base: str
    time_smoothness: float
    gs_windows_per_step: int
    stop_at_noise: bool
    stall_drop: float
    stall_passes: int
    ema_decay: float
    motion_init: str = "flow"
    motion_model: str = "field"
    matte_l1: float = 0.0
    fields: dict = field(default_factory=dict)



# _Resolved's values that a None setting takes from the preset (rows_per_step also: capped by H).
_FROM_PRESET = ("beta", "tau", "lr", "lr_half_life_steps", "init", "dynamic_time", "dynamic_base", "time_smoothness",
                "gs_windows_per_step", "stop_at_noise", "stall_drop", "stall_passes", "ema_decay", "motion_init",
                "motion_model", "matte_l1")


def chunk_frames(settings: STFMSettings, h: int, w: int, device: str | None = None) -> int:
    """Frames per autograd graph: the setting, else as many as hold CHUNK_POINTS pixels (at least 4);
    on a CUDA `device`, GPU_CHUNK_POINTS, or what an eighth of its memory holds where that is less."""
    if settings.frame_chunk:
        return settings.frame_chunk
    points = CHUNK_POINTS
    if device is not None and str(device).startswith("cuda"):
        card = torch.cuda.get_device_properties(torch.device(device)).total_memory
        points = max(CHUNK_POINTS, min(GPU_CHUNK_POINTS, card // (GPU_GRAPH_SHARE * GRAPH_BYTES_PER_POINT)))
    return max(MIN_FRAME_CHUNK, points // max(1, h * w))


def resolve(settings: STFMSettings, h: int, w: int, k: int) -> tuple[_Resolved, dict]:
    """The settings for an H x W x K video with every None filled from the preset, and the preset
    (its field configurations and learning-rate ratios)."""
    preset = _preset(settings.preset, h, w, k)
    values = {name: preset[name] if getattr(settings, name) is None else getattr(settings, name)
              for name in _FROM_PRESET}
    # the preset's tau is for its own motion model; another model, with the preset's tau, gets its share
    if values["motion_model"] != preset["motion_model"] and settings.tau in (None, preset["tau"]):
        values["tau"] *= TRANSLATION_TV_SHARE if values["motion_model"] == "translation" else 1 / TRANSLATION_TV_SHARE
    return _Resolved(settings=settings, rows_per_step=min(h, settings.rows_per_step or preset["rows_per_step"]),
                     fields={key: preset[key] for key in ("static", "motion", "dynamic")}, **values), preset


# What the registry's presets (the command line, the Python API by label) add to the dataclass's
# defaults: the gains refined from the data before the fit and the GS-only start as the floor of the
# output (rngcam.recon.methods.selfcal, rngcam.recon.methods.stfm.floor), and the GS-to-RS transform learned
# with the fields (rngcam.recon.methods.stfm.model.FieldModel.gs_matrix). The dataclass keeps them off, so that a
# fit built from STFMSettings directly is exactly the model and nothing around it.
USER_DEFAULTS = {"self_calibrate": "gains", "start_floor": True, "learn_geometry": "shift", "learn_line_time": "auto"}


SIZE_DEPENDENT = ("rows_per_step", "stall_passes")  # preset values that depend on the grid (_preset's h)


def preset_settings(name: str) -> STFMSettings:
    """Preset `name` as settings: every value that does not depend on the problem's size filled in
    (what the registry offers and `--help` shows); the others stay None (resolved per problem).
    "auto" fills nothing: make_stfm picks prior or fast per scene and fills from that one."""
    if name == "auto":
        return STFMSettings(preset="auto", **USER_DEFAULTS)
    values = _preset(name, 2, 2, 2)
    user = {} if name == "paper" else USER_DEFAULTS  # paper: the paper's method as published
    return replace(STFMSettings(preset=name, **user), **{f.name: values[f.name] for f in fields(STFMSettings)
                                                          if f.name in values and f.name not in SIZE_DEPENDENT})


def _setting_or_preset(settings: STFMSettings, name: str):
    """A setting's value, or its preset's where the setting is None (for values that do not
    depend on the problem's size)."""
    value = getattr(settings, name)
    return _preset(settings.preset, 2, 2, 2)[name] if value is None else value


def _base_list(bases: str) -> list[str]:
    """The dynamic bases of a `dynamic_base` setting ("ensemble" is ENSEMBLE_BASES)."""
    return (ENSEMBLE_BASES if bases == "ensemble" else bases).split(",")


