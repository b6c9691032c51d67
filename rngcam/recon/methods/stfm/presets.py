"""STFM's named presets as data: each preset's field configurations and schedule (`preset_table`).

A preset is a table: the fields' architectures, the learning rates, the regularisation weights and the
stop tests' windows. `paper` is the paper's method as published; `fast` the feature-plane fields on a
GS-only base video (the default); `prior` the paper's prior (one canonical dynamic image that a motion
moves) on the fast fields. Entries that depend on the grid (plane resolutions, rows a step, the stall
window) are filled by `preset_table` from the problem's size. Each number's reason and the bench/ table
that measured it is next to it.
"""

from __future__ import annotations

import math

from rngcam.errors import ConfigError

# The stall test compares the RS residual with its value this many passes over the RS rows ago (fast)
STALL_PASSES = 15
# The prior preset's window: over 30 passes a lull stopped some fits early, well under the same capture's
# other seeds (bench/convergence.md, "the prior preset's stall window 30 -> 45 passes"; bench/realistic.md)
PRIOR_STALL_PASSES = 45
# ... and on grids of at most SMALL_STALL_SIDE rows (the half grid of a 64 px run, whose full level refines
# it): fewer steps for the same result (bench/convergence.md, "the half grid first again")
SMALL_STALL_PASSES, SMALL_STALL_SIDE = 10, 32
# A translation's motion TV is paid at every pixel, a field's mostly where the object moves: a
# translation's tau is a field's times this (about a small object's share of the frame).
# At a field's tau the ball's path was cut at its turns (bench/stfm_motion.md).
TRANSLATION_TV_SHARE = 0.02
DYNAMIC_FEATURES = 4  # features per plane of the fast dynamic field (8 was slower and no better)

# The paper's SIREN fields and schedule (every entry but rows_per_step, a quarter of the rows a step)
_SIREN = {"w0": 30.0, "n_freqs": 6}
PAPER = {
    "static": ("siren", dict(hidden=32, layers=2, **_SIREN)),
    "motion": ("siren", dict(hidden=32, layers=2, **_SIREN)),
    "dynamic": ("siren", dict(hidden=128, layers=3, **_SIREN)),
    "lr": 5e-6, "decoder_lr_ratio": 1.0, "gain_lr_ratio": 1.0, "lr_half_life_steps": math.inf,
    "beta": 10.0, "tau": 1e-3, "init": "random",
    "dynamic_time": False, "dynamic_base": "none", "gs_windows_per_step": 0, "time_smoothness": 0.0,
    "stop_at_noise": False, "stall_drop": 0.0, "stall_passes": STALL_PASSES, "ema_decay": 0.0,
    "refine": False, "motion_init": "flow", "motion_model": "field",
    "matte_l1": 0.0, "subframes": 1, "fits": 1}
PAPER_ROWS_FRACTION = 4  # rows a step: the rows over this

# The fast preset's feature-plane fields: plane sides as fractions of the longer side (appearance) and of
# it (motion, coarser), plane lengths in time as fractions of the frames; the decoders' width
APPEARANCE_SCALES = (0.25, 0.5, 1.0)
MOTION_SCALES = (1 / 16, 1 / 8, 1 / 4)
TIME_SCALES = (0.25, 0.5, 1.0)
PLANE_FEATURES, PLANE_HIDDEN = 8, 32
# Its schedule and regularisation (every entry but the fields, rows_per_step and stall_passes)
FAST = {
    "lr": 1e-2, "decoder_lr_ratio": 0.25, "gain_lr_ratio": 0.01, "lr_half_life_steps": 400.0,
    "beta": 1.0, "tau": 1e-4, "init": "gs",
    "dynamic_time": True, "dynamic_base": "ensemble", "gs_windows_per_step": 1, "time_smoothness": 0.3,
    "stop_at_noise": True, "stall_drop": 0.02, "ema_decay": 0.95, "refine": True,
    "motion_init": "flow", "motion_model": "field",
    "matte_l1": 0.0, "subframes": 1, "fits": 1}
# rows a step: 8, a quarter of the rows below 32 px (the half grid of a 64 px run: 8 rows, not the
# 4 of h // 8: less time and a better result; bench/convergence.md, "the fast preset on the half grid first")
FAST_ROWS, FAST_ROWS_FRACTION = 8, 4

# What the prior preset changes of the fast one (the paper's prior on the fast fields: one canonical
# dynamic image that the motion moves; its dynamic field has no time planes)
PRIOR = {
    "dynamic_time": False, "dynamic_base": "none", "refine": False, "motion_init": "search",
    # One translation per frame: the scenes auto gives prior are those one translating
    # layer explains, and a motion field, even 10x stiffer in space, tore the canonical
    # image (sineball 64 px: a round ball in every frame; bench/stfm_motion.md). Its tau
    # below is a translation's: TRANSLATION_TV_SHARE of the field's 1e-3.
    "motion_model": "translation",
    # A slow stall test: 2 % over 15 passes stopped it while it was still gaining
    # (bench/stfm_motion.md); on captures its model cannot fit to the noise level it
    # settles later (bench/realistic.md), and without a stop the result
    # depended on how many steps the time budget allowed, i.e. on the machine's load.
    "stall_drop": 0.001, "stall_passes": PRIOR_STALL_PASSES,
    # A nearly rigid motion (spatial TV 10x fast's, temporal the same): a motion that
    # varies across the object tears the canonical image (bench/stfm_motion.md).
    "beta": 0.1, "tau": 1e-3 * TRANSLATION_TV_SHARE,
    # The canonical image starts from a motion-blurred key frame whose matte covers the
    # whole smear: without this its edge stays as a rim and shadow (bench/stfm_motion.md).
    "matte_l1": 0.02,
    # Half-frames: the rows' exposures begin and end inside frames while the layer moves
    # several pixels a frame; the output's frames alone put the ball where a row saw it
    # early or late in the frame (bench/realistic.md, "the prior preset fits half-frames").
    "subframes": 2,
    # Two fits from seeds 0 and 1, averaged: what the RS rows do not pin differs between
    # them and averages out (better than either fit, or than picking the one with the
    # lower RS residual), at twice the compute (bench/realistic.md, "the prior preset
    # averages two fits")
    "fits": 2}
# an eighth of the rows a step (at most FAST_ROWS): with 8 rows below 64 px its 48 px translation test
# flipped (bench/convergence.md, "the fast preset on the half grid first")
PRIOR_ROWS_FRACTION = 8


def _scales(fractions, n: int) -> tuple:
    """Plane sizes: `n` times each fraction, at least 2, distinct and sorted."""
    return tuple(sorted({max(2, round(n * f)) for f in fractions}))


def _time_for(space: tuple, k: int) -> tuple:
    """Plane lengths in time for planes of sides `space` on `k` frames (the longest repeated)."""
    t = tuple(max(2, round(k * f)) for f in TIME_SCALES)[:len(space)]
    return t + (t[-1],) * (len(space) - len(t))


def preset_table(name: str, h: int, w: int, k: int) -> dict:
    """Field configurations and schedule of a preset for an H x W x K video."""
    if name == "auto":
        raise ConfigError("preset 'auto' chooses another preset: build the method with make_stfm")
    if name == "paper":
        return {**PAPER, "rows_per_step": max(1, h // PAPER_ROWS_FRACTION)}
    side = max(h, w)
    appearance = _scales(APPEARANCE_SCALES, side)
    motion_space = _scales(MOTION_SCALES, side)
    motion_time = _time_for(motion_space, k)
    plane = {"features": PLANE_FEATURES, "hidden": PLANE_HIDDEN}
    fast = {
        "static": ("planes", {"resolutions": appearance, **plane}),
        "motion": ("planes", {"resolutions": motion_space, "time_resolutions": motion_time, **plane}),
        "dynamic": ("planes", {"resolutions": appearance, "time_resolutions": _time_for(appearance, k),
                                "features": DYNAMIC_FEATURES, "hidden": PLANE_HIDDEN}),
        **FAST,
        "rows_per_step": max(1, min(FAST_ROWS, h // FAST_ROWS_FRACTION)),
        "stall_passes": SMALL_STALL_PASSES if h <= SMALL_STALL_SIDE else STALL_PASSES}
    if name == "prior":
        fast.update({"dynamic": ("planes", {"resolutions": appearance, "features": DYNAMIC_FEATURES,
                                            "hidden": PLANE_HIDDEN}),
                     **PRIOR,
                     "rows_per_step": max(1, min(FAST_ROWS, h // PRIOR_ROWS_FRACTION))})
    return fast
