"""The space-time fusion model (STFM), rngcam's neural reconstruction (RnGCam, ICCV 2025).

A static field, a motion field and a dynamic field, composited with a matte and fitted to the RS
and GS measurements; docs/design.md ("STFM's model") describes the model, its loss, its steps, its
stopping rules and its presets; the figures behind them are in bench/ (stfm_history.md,
stfm_compare.md, stfm_motion.md).

Modules: settings (STFMSettings, the presets), model (fields -> frames), fields (feature-plane
fields and their transfer between grids), bases (the dynamic field's base videos), loss (data
terms through rngcam.physics.operators, TV), init (from the GS frames), stopping (noise and stall
tests), motion_search (the prior preset's motion start), method (STFM: one fit), ensemble
(STFMEnsemble, make_stfm), multilevel (coarse to fine), auto (`preset="auto"`'s per-scene choice),
floor (the GS-only floor of the output), components (which parts a scene needs); stage, stages and
recipe (the stages every build runs, make_stfm), build_fit (the fit stage).
"""

from rngcam.recon.methods.stfm.ensemble import STFMEnsemble
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.recipe import RECIPE, explain, make_stfm
from rngcam.recon.methods.stfm.settings import (
    ALL_BASES,
    ENSEMBLE_BASES,
    INIT_STEPS,
    NOISE_CHECK_STEPS,
    PRESETS,
    REFINE_LR_RATIO,
    REFINE_STALL_PASSES,
    STALL_PASSES,
    STFMSettings,
)

__all__ = ["ALL_BASES", "ENSEMBLE_BASES", "INIT_STEPS", "NOISE_CHECK_STEPS", "PRESETS", "RECIPE", "REFINE_LR_RATIO",
           "REFINE_STALL_PASSES", "explain", "STALL_PASSES", "STFM", "STFMEnsemble", "STFMSettings", "make_stfm"]
