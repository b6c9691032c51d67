"""The recipe's fit stage: which fit a build makes (one fit, an ensemble, coarse to fine), and a later
whole run made for a refit stage."""

from __future__ import annotations

from dataclasses import replace

from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.methods.selfcal import calibrate_problem
from rngcam.recon.methods.stfm.ensemble import STFMEnsemble
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.multilevel import make_multilevel, stfm_levels
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.methods.stfm.settings import STFMSettings, _base_list, _setting_or_preset


def make_fit(problem, settings: STFMSettings, device, initial_video: Tensor | None, clock=None, stage=None,
             state: RunState | None = None, nested=None):
    """The fit of a build: coarse to fine where `stfm_levels` gives several levels, else one STFM on
    `initial_video` (a level above the coarsest), one fit, or an ensemble of bases or seeds; each fit
    carries `state` (what the build found); `nested(problem, settings, device, state=...)` builds a
    level (the recipe's make_stfm)."""
    state = state or RunState()
    if initial_video is None:
        factors = stfm_levels(problem, settings)
        if len(factors) > 1:
            return make_multilevel(problem, settings, device, factors,
                                   lambda level, s: nested(level, s, device, state=state), clock, stage)
    if initial_video is not None:
        if tuple(initial_video.shape) != tuple(problem.shape):
            raise ConfigError(f"initial_video has shape {tuple(initial_video.shape)}, the problem's video "
                              f"is {tuple(problem.shape)}")
        return STFM(problem, replace(settings, dynamic_base="video", dynamic_time=True), device,
                    base_video=initial_video, state=state)
    names = _base_list(_setting_or_preset(settings, "dynamic_base"))
    fits = _setting_or_preset(settings, "fits")
    if len(names) == 1 and fits == 1:
        return STFM(problem, replace(settings, dynamic_base=names[0]), device, state=state)
    first = STFM(problem, replace(settings, dynamic_base=names[0]), device, state=state)
    if len(names) == 1:  # one base, fitted `fits` times from consecutive seeds
        return STFMEnsemble(first.problem, settings, names * fits, device, first=first, clock=clock)
    if first.base.source is None:  # no dynamic base applies (no GS frames, no motion, ...): one fit
        return first
    # first.problem is float32 on the device: the other fits share its tensors instead of casting again
    return STFMEnsemble(first.problem, settings, names, device, first=first)


def describe_fit(problem, settings: STFMSettings, initial_video: Tensor | None) -> str:
    """One clause: the fit `make_fit` makes for these, without making it."""
    if initial_video is not None:
        return "one fit on the given video"
    c, k, h, w = problem.shape
    factors = stfm_levels(problem, settings)
    levels = "" if len(factors) == 1 else f"coarse to fine at 1/{', 1/'.join(map(str, factors))} of the grid; "
    names = _base_list(_setting_or_preset(settings, "dynamic_base"))
    fits = _setting_or_preset(settings, "fits")
    if len(names) == 1 and fits == 1:
        what = f"one fit on base {names[0]}"
    elif len(names) == 1:
        what = f"{fits} fits of base {names[0]} from seeds {settings.seed}-{settings.seed + fits - 1}, averaged"
    else:
        refine = " then refined" if _setting_or_preset(settings, "refine") else ""
        what = f"{len(names)} fits on bases {', '.join(names)}, averaged{refine}"
    return f"{levels}{what}; preset {settings.preset}, {k} frames of {h}x{w}"


def another_fit(build, changed, found: dict, psf_scale: bool, made_from: dict, **off):
    """A later fit of a refit stage: a whole STFM run on `changed` (the problem as handed, changed),
    calibrated again as the first was (what the stage found kept in its report), made from `made_from`
    (RunState fields), with the settings `off` given and no track or preset refit (those stages wrap the
    first whole run only)."""
    settings = build.settings
    changed = replace(changed, notes=list(changed.notes))
    calibration = build.state.selfcal_report
    if settings.self_calibrate != "off":
        changed, calibration = calibrate_problem(changed, settings.self_calibrate, psf_scale)
        calibration = dict(calibration or {}, **found)
    state = replace(build.state, selfcal_report=calibration, **made_from)
    later = replace(settings, track_refit=False, preset_refit=False, **off)
    return build.nested(changed, later, build.device, clock=build.clock, stage=build.stage, state=state)
