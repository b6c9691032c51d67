"""Each STFMSettings field's `--set STAGE.KEY` spelling, under the stage of the recipe that owns it.

The command line's one way to change an STFM setting: `--set fit.tau=1e-4`, `--set line_refit.enabled=false`
or the same in a `--recipe` file (rngcam.recon.methods.stfm.recipe.with_stage_settings). A key here must not be
a field of its stage's config (stage_configs.py), which `--set` changes the same way.
"""

from __future__ import annotations

import math
import typing

from rngcam.recon.methods.stfm.settings import STFMSettings, _setting_or_preset, chunk_frames, resolve

# (stage, key) -> STFMSettings field. Not here: `preset` (--preset) and `stages` (the configs themselves).
SETTING_NAMES: dict[tuple[str, str], str] = {
    ("self_calibration", "mode"): "self_calibrate",
    ("self_calibration", "psf_scale"): "self_calibrate_psf_scale",
    ("subframes", "count"): "subframes",
    # the model: its fields, their weights and what the fit leaves out (the paper's ablations)
    ("fit", "components"): "components",
    ("fit", "no_static"): "no_static",
    ("fit", "no_motion_reg"): "no_motion_reg",
    ("fit", "no_rs"): "no_rs",
    ("fit", "no_gs"): "no_gs",
    ("fit", "gs_anchor"): "gs_anchor",
    ("fit", "beta"): "beta",
    ("fit", "tau"): "tau",
    ("fit", "psi"): "psi",
    ("fit", "matte_l1"): "matte_l1",
    ("fit", "time_smoothness"): "time_smoothness",
    ("fit", "base"): "dynamic_base",
    ("fit", "dynamic_time"): "dynamic_time",
    ("fit", "motion_model"): "motion_model",
    ("fit", "motion_init"): "motion_init",
    ("fit", "init"): "init",
    ("fit", "learn_geometry"): "learn_geometry",
    ("fit", "learn_line_time"): "learn_line_time",
    # the schedule: how many fits, on which grids, with which steps, and when they stop
    ("fit", "fits"): "fits",
    ("fit", "refine"): "refine",
    ("fit", "coarse_to_fine"): "coarse_to_fine",
    ("fit", "seed"): "seed",
    ("fit", "lr"): "lr",
    ("fit", "lr_half_life_steps"): "lr_half_life_steps",
    ("fit", "rows_per_step"): "rows_per_step",
    ("fit", "tv_frames_per_step"): "tv_frames_per_step",
    ("fit", "gs_windows_per_step"): "gs_windows_per_step",
    ("fit", "frame_chunk"): "frame_chunk",
    ("fit", "ema_decay"): "ema_decay",
    ("fit", "stop_at_noise"): "stop_at_noise",
    ("fit", "stall_drop"): "stall_drop",
    ("fit", "stall_passes"): "stall_passes",
    ("start_floor", "enabled"): "start_floor",
    ("line_refit", "enabled"): "line_refit",
    ("psf_edge", "enabled"): "psf_edge",
    ("row_gain_refit", "enabled"): "row_gain_refit",
    ("track_refit", "enabled"): "track_refit",
    ("preset_refit", "enabled"): "preset_refit",
}
NOT_NAMED = ("preset", "stages")  # --preset; the stages' configs


def keys_of(stage: str) -> tuple[str, ...]:
    """The settings fields' keys under `stage`, in the table's order."""
    return tuple(key for s, key in SETTING_NAMES if s == stage)


def spelling(field_name: str) -> str | None:
    """`STAGE.KEY` of an STFMSettings field (None for one that has none)."""
    return next((f"{s}.{key}" for (s, key), name in SETTING_NAMES.items() if name == field_name), None)


def field_type(field_name: str) -> type:
    """The field's type without None (float | None -> float)."""
    hint = typing.get_type_hints(STFMSettings)[field_name]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if args else hint


def stage_values(settings: STFMSettings, stage: str, shape: tuple[int, int, int, int] | None = None) -> dict:
    """The values of the settings `stage` owns, by key, as a build of that `shape` (C, K, H, W) resolves
    them: a value the preset fills in (None in `settings`) as the preset's, where the preset is known."""
    keys = keys_of(stage)
    if not keys:
        return {}
    resolved = None
    if settings.preset != "auto" and shape is not None:
        _, k, h, w = shape
        resolved = resolve(settings, h, w, k)[0]
    out = {}
    for key in keys:
        name = SETTING_NAMES[(stage, key)]
        value = getattr(settings, name)
        if value is None and settings.preset != "auto":
            if resolved is not None and hasattr(resolved, name):
                value = getattr(resolved, name)
            elif name == "frame_chunk" and shape is not None:
                value = chunk_frames(settings, shape[2], shape[3])
            else:
                try:
                    value = _setting_or_preset(settings, name)
                except KeyError:  # a value only a build decides
                    value = None
        out[key] = _shown(value)
    return out


def _shown(value):
    if value is None:
        return "the preset's"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return value

