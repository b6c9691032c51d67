"""The misfit verdict: does the model explain the data the run fitted?

An iterative fit whose forward model is right ends with its RS residual near the noise level it
estimated from the RS image (STFM and pnp stop there). One that stops clearly above it is fitting
data the model does not explain: a PSF at another magnification than the calibration's (a scene at
another depth), a GS-to-RS transform off, a line time off. `verdict` says so in one line and names
the causes the run did not correct (from what self-calibration estimated and applied and what
the fit learned with its fields); a run whose residual reached the noise level gets None, unless
the line time it learned, or the GS-to-RS shift self-calibration's key rows pinned (the fit's, where
there are no key rows), is far off the recorded one ("calibration far off": the recorded calibration
is wrong, and what the fit learned of it rests on the motion: the line time on a motion timing the
rows, the shift only across the motion). The
threshold is set above what the fine simulation family ends on (the model right up to sub-grid
detail; bench/realistic.md).
"""

from __future__ import annotations

import math

# RS residual / noise level above which the data are not explained: the fine family and the lab
# family end below it, a PSF a few percent off above (bench/realistic.md, "Misfit verdict").
# Where self-calibration's key rows found a PSF scale it did not apply, the lower one.
MISFIT_RATIO = 1.2
# A fit that ends at this many times its noise level or more is not explained: STFM's PSF-edge, row-gain and
# track stages fit again from it, another error (a PSF at another scale) moves its line time, so one later
# line fit from it at most, and it is stopped where it stalls, not run on (the fit reads it as
# `--set fit.explained_ratio`; bench/realistic.md, "a run left unexplained is made again from a softer motion
# search"). Where the key rows pointed at a cause, the verdict speaks from it too.
EXPLAINED_RATIO = 1.15
POINTED_RATIO = EXPLAINED_RATIO
# A run whose last level refines a coarser level's estimate (coarse to fine: the fast preset from 64 px)
# ends a little further from the noise level: that fit starts from the half grid's video and stops when it
# stalls, where a fit from the GS-only bases fits the RS image from scratch. The fine and lab families end
# below this, a PSF 5 % large above (bench/convergence.md, "the half grid first again").
MISFIT_RATIO_LEVELS = 1.35

# The key rows (the RS rows exposed with the GS frames, where the video is the GS frames) explained to this many
# times the RS noise level after self-calibration say the calibration the fit uses is consistent: across the
# untuned scene set with exact or calibrated calibration they end at 0.99-1.48x (low light highest), with the PSF
# 5 % large at 1.75-3.41x but on the low-light scene (1.50x: its noise hides it); they do not see a line time or
# a shift off (bench/untuned.md, "key rows against calibration errors"). A run left above the noise
# level with its key rows explained has motion between the key frames the model does not represent: it says so
# (above_noise) without blaming the calibration.
KEY_ROWS_EXPLAINED = 1.7
NOT_EXPLAINED = "model does not explain the data"
NOT_FITTED = "data not fitted yet"
FAR_OFF = "calibration far off"
# A learned line-time factor this far from 1 says the recorded line time is wrong, not rough: on half-frames
# what exact timing wanders and what the lab family's +-0.5 % is learned as stay under it; a capture 2 %
# long is learned nearly whole over later fits (stfm/line_refit.py), where one moving object times the rows
# (bench/realistic.md, "the prior preset fits half-frames" and "the line time learned on over later fits").
LINE_TIME_FAR = 0.007
# ... and one this far from 1 makes the fit's note suggest measuring the line time: above what the fit wanders
# on exact timing (bench/realistic.md, "the prior preset fits half-frames")
LINE_TIME_SUSPECT = 0.005
# A GS-to-RS shift this far (px) from the calibration's says the calibration is off; `calibrate align` on a
# static chart leaves far less (bench/realistic.md, "what the fit cannot learn").
GEOMETRY_FAR_PX = 0.6
# Where self-calibration's key rows (exposed with the GS frames: no motion between them) measured the shift, they
# decide, and only where they pin it: its length at least this many standard errors, with a rotation and scale
# such as a calibration leaves (`transform_plausible`). The shift the fit learns trades against the scene's
# motion: on exact captures it learned 1.01 px (a shaking camera) and 1.36 px (a dim scene), where the key rows
# read 0.06 +/- 0.1 px and an implausible transform; over 37 exact and calibrated bundles the key rows give no
# verdict, over 12 with a 1 px shift 10 (bench/untuned.md, "the shift verdict from the key rows").
KEY_ROWS_SHIFT_Z = 3.0


def _causes(selfcal: dict | None, gs_fitted: bool = True, learned: tuple[str, ...] = ()) -> tuple[list[str], bool]:
    """(what the run could not correct, whether the key rows pointed at one of them): the
    calibration values self-calibration did not apply and the fit did not learn (`learned`:
    "geometry", "line time"), a PSF scale it found off by more than 1 % and did not apply first;
    the GS-to-RS transform only where GS frames were fitted; a PSF scale it applied last (the
    estimate can take up another error, as a line-time error did; bench/realistic.md), or
    the shrink a second fit used with the PSF's lost edge fitted (report["psf_edge"]). (The
    key rows' GS-to-RS transform is too loosely pinned to point.)"""
    report = selfcal if isinstance(selfcal, dict) else {}  # a foreign metrics.json may hold anything
    scales = report.get("scales")
    psf = scales.get("psf") if isinstance(scales, dict) else None
    psf = psf if isinstance(psf, dict) else None
    edge = report.get("psf_edge") if isinstance(report.get("psf_edge"), dict) else {}
    kept = edge.get("kept")  # the output: the first fit (0), or one through a fitted edge
    edge_scale = _number(edge.get("scale")) if isinstance(kept, int) and kept > 0 else None
    causes = []
    estimate = _number(psf.get("estimate")) if psf else None
    pointed = bool(estimate is not None and not psf.get("applied") and abs(estimate - 1) > 0.01 and edge_scale is None)
    if edge_scale is not None:
        causes.append(f"PSF scale (x{edge_scale:.3f} with its lost edge fitted; perhaps another error taken for it)")
    elif not (psf and psf.get("applied")):
        causes.append("PSF scale")
    if gs_fitted and "geometry" not in learned and (not report.get("applied") or "transform_not_applied" in report):
        causes.append("geometry")
    if "line time" not in learned:  # the key rows do not carry it
        causes.append("line time")
    if psf and psf.get("applied"):  # the estimate can take up another error (bench/realistic.md)
        end = _number(psf.get("end", psf.get("estimate")))
        causes.append(f"PSF scale ({'' if end is None else f'x{end:.3f} '}applied; perhaps another error taken for it)")
    return causes, pointed


def _number(value) -> float | None:
    """A finite float, else None."""
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def learned_by_fit(method_results: dict | None) -> tuple[str, ...]:
    """What the fit learned with its fields, from its resolved settings (method_results)."""
    found = method_results or {}
    return tuple(name for name, key in (("geometry", "gs_geometry"), ("line time", "line_time")) if found.get(key))


def verdict(rs_residual, noise_level, selfcal: dict | None = None, ended_by: str = "own_stop",
            status: str = "ok", ratio_limit: float = MISFIT_RATIO, gs_fitted: bool = True,
            learned: tuple[str, ...] = (), line_factor: float | None = None,
            learned_shift_px: float | None = None, line_refuted: bool = False) -> dict | None:
    """None when the RS residual is within `ratio_limit` x the noise level (POINTED_RATIO where the
    key rows found a PSF scale not applied), or either is unknown, or the run did not finish
    cleanly; else {"verdict", "rs_residual", "noise_level", "ratio", "threshold", "likely_causes",
    "line"}. `selfcal`: STFM's self-calibration report (method_results' self_calibration);
    `gs_fitted`: False under --no-gs, where the GS-to-RS transform plays no part; `learned`: the
    causes the fit corrected itself (`learned_by_fit`); `line_factor`: the line-time factor it
    learned, `learned_shift_px`: the length of the GS-to-RS shift it learned: more than LINE_TIME_FAR
    from 1, or a shift GEOMETRY_FAR_PX long (the key rows' in `selfcal` where they measured it, pinned at
    KEY_ROWS_SHIFT_Z standard errors; else the fit's), a residual within the limit gives the FAR_OFF verdict
    (explained data, a recorded calibration off by more than the fit corrects reliably), unless
    `line_refuted` (`line_time_refuted`: a fit started at the learned factor explained the RS image worse)."""
    try:
        residual, noise = float(rs_residual), float(noise_level)
    except (TypeError, ValueError):
        return None
    if status != "ok" or ended_by == "one_shot" or not (math.isfinite(residual) and math.isfinite(noise)
                                                         and noise > 0):
        return None
    ratio = residual / noise
    causes, pointed = _causes(selfcal, gs_fitted, learned)
    limit = min(ratio_limit, POINTED_RATIO) if pointed else ratio_limit
    key_shift = key_rows_shift(selfcal) if gs_fitted else None
    if ratio <= limit:
        return _far_off(None if line_refuted else line_factor, learned_shift_px if gs_fitted else None, key_shift,
                        residual, noise, ratio, limit)
    finished = ended_by == "own_stop"
    key = key_rows_ratio(selfcal, noise) if gs_fitted else None
    # the key rows fit the transform, so a shifted GS camera leaves them explained: a shift they pin still speaks
    shifted = _pinned(key_shift)
    # a line time learned far off speaks too: the key rows do not see it (shake 2 % long, cut by the budget at
    # 1.27x the noise, learned x1.0152: bench/untuned.md, "a line time off, on whole runs")
    line_far = not line_refuted and _line_far(line_factor)
    if finished and not (pointed or shifted or line_far) and key is not None and key <= KEY_ROWS_EXPLAINED:
        return None  # the calibration explains the key rows: motion is what is left (above_noise says so)
    if shifted:
        causes = ["geometry"] + [c for c in causes if c != "geometry"]
    if line_far:
        causes = ["line time"] + [c for c in causes if c != "line time"]
    what = NOT_EXPLAINED if finished else NOT_FITTED
    line = (f"misfit: {what}: RS residual {residual:.4f} is {ratio:.2f}x the noise level {noise:.4f}")
    if finished:
        line += f"; likely causes not corrected: {', '.join(causes)}"
        if shifted:
            line += (f" (the key rows put the GS frames at a GS-to-RS shift of {key_shift[0]:.2f} px (+/- "
                     f"{key_shift[1]:.2f}) from the calibration's: measure it with `rngcam calibrate align`)")
        if pointed:
            psf = selfcal["scales"]["psf"]
            why = f": {psf['why']}" if isinstance(psf.get("why"), str) else ""
            line += f" (the key rows suggest a PSF scale of {float(psf['estimate']):.3f}, not applied{why})"
    else:
        line += f" (ended by {ended_by} before its own stop: more iterations, or {', '.join(causes)})"
    if line_far:
        line += (f"; the fit learned the RS line time at x{_number(line_factor):.4f} the recorded one: measure it with "
                 "`rngcam calibrate linetime --flicker`")
    found = {"verdict": what, "rs_residual": residual, "noise_level": noise, "ratio": ratio,
             "threshold": limit, "likely_causes": causes, "line": line}
    return {**found, "line_factor": _number(line_factor)} if line_far else found


def key_rows_ratio(selfcal, noise: float) -> float | None:
    """The key rows' relative RS residual after self-calibration over the RS noise level, or None (no
    self-calibration report of rngcam's shape)."""
    report = selfcal if isinstance(selfcal, dict) else {}
    after = _number(report.get("rs_residual_after"))
    return after / noise if after is not None and noise > 0 else None


def key_rows_shift(selfcal) -> tuple[float, float] | None | bool:
    """(length, its standard error) in px of the GS-to-RS shift self-calibration's key rows measured, where
    their transform is plausible; False where a key-row report of rngcam's shape says nothing pins it
    (an implausible transform, no standard errors); None without one (metrics from elsewhere, no key rows)."""
    report = selfcal if isinstance(selfcal, dict) else {}
    measured = report.get("transform_rejected", report.get("refined"))
    sigma = report.get("sigma")
    if "transform_plausible" not in report or not isinstance(measured, dict) or not isinstance(sigma, dict):
        return None
    shift = measured.get("shift_px")
    if report["transform_plausible"] is not True or not (isinstance(shift, list) and len(shift) == 2):
        return False
    dx, dy, sx, sy = (_number(v) for v in (*shift, sigma.get("shift_x_px"), sigma.get("shift_y_px")))
    if None in (dx, dy, sx, sy):
        return False
    length = math.hypot(dx, dy)
    along = math.hypot(dx * sx, dy * sy) / length if length > 0 else max(sx, sy)  # the error along the shift
    return length, along


def _pinned(key_shift) -> bool:
    """Whether the key rows' shift (key_rows_shift's) is far off the calibration's and pinned."""
    return bool(key_shift) and key_shift[0] > max(GEOMETRY_FAR_PX, KEY_ROWS_SHIFT_Z * key_shift[1])


def _far_off(line_factor, shift_px, key_shift, residual: float, noise: float, ratio: float,
             limit: float) -> dict | None:
    """The verdict where the data are explained but the fit learned a line time, or the key rows (else the fit)
    a GS-to-RS shift, far off the recorded calibration (`key_shift`: key_rows_shift's)."""
    line_factor, shift_px = _number(line_factor), _number(shift_px)
    line_far = _line_far(line_factor)
    if key_shift is None:  # no key rows: the fit's shift is all there is
        shift_far = shift_px is not None and shift_px > GEOMETRY_FAR_PX
    else:
        shift_far = _pinned(key_shift)
    if not (line_far or shift_far):
        return None
    parts, causes = [], []
    if line_far:
        parts.append(f"the fit learned the RS line time at x{line_factor:.4f} the recorded one; an error beyond "
                     f"{100 * LINE_TIME_FAR:g} % is learned over several fits and only where one moving object times "
                     "the rows (elsewhere moving objects may be misplaced in the last rows' frames): measure it with "
                     "`rngcam calibrate linetime --flicker`")
        causes.append("line time")
    if shift_far and key_shift:
        learned = "" if shift_px is None else f"; the fit learned {shift_px:.2f} px"
        parts.append(f"the key rows (the RS rows exposed with the GS frames) put the GS frames at a GS-to-RS shift of "
                     f"{key_shift[0]:.2f} px (+/- {key_shift[1]:.2f}) from the calibration's{learned}: measure it with "
                     "`rngcam calibrate align`")
        causes.append("geometry")
    elif shift_far:
        parts.append(f"the fit learned a GS-to-RS shift of {shift_px:.2f} px on top of the calibration's; it pins the "
                     "shift across the scene's motion only (along it the shift trades against the motion's timing) and "
                     "applies it on the reconstruction's grid, where detail finer than a grid pixel aliases: "
                     "measure it with `rngcam calibrate align`")
        causes.append("geometry")
    line = f"misfit: {FAR_OFF}: " + "; ".join(parts) + " and reconstruct again"
    found = {"verdict": FAR_OFF, "rs_residual": residual, "noise_level": noise, "ratio": ratio, "threshold": limit,
             "likely_causes": causes, "line": line}
    if line_far:
        found["line_factor"] = line_factor
    if shift_far and shift_px is not None:
        found["learned_shift_px"] = shift_px
    if shift_far and key_shift:
        found["key_rows_shift_px"] = key_shift[0]
    return found


def _line_far(line_factor) -> bool:
    """Whether a learned line-time factor is more than LINE_TIME_FAR from 1."""
    factor = _number(line_factor)
    return factor is not None and abs(factor - 1) > LINE_TIME_FAR


def ratio_limit(levels) -> float:
    """The residual / noise ratio above which a run is unexplained: MISFIT_RATIO_LEVELS where it went
    coarse to fine (`levels`: method_results' list of levels), else MISFIT_RATIO."""
    return MISFIT_RATIO_LEVELS if isinstance(levels, list) and len(levels) > 1 else MISFIT_RATIO


def for_metrics(metrics: dict) -> dict | None:
    """The verdict for a run's metrics (residual_rs, method_results' noise level, self-calibration and
    levels: MISFIT_RATIO_LEVELS where the run went coarse to fine)."""
    found = metrics.get("method_results") or {}
    gs_fitted = not (metrics.get("method_settings") or {}).get("no_gs")
    line = found.get("line_time") if isinstance(found.get("line_time"), dict) else {}
    return verdict(metrics.get("residual_rs"), found.get("rs_noise_level"), found.get("self_calibration"),
                   metrics.get("ended_by", "own_stop"), metrics.get("status", "ok"),
                   ratio_limit=ratio_limit(found.get("levels")),
                   gs_fitted=gs_fitted, learned=learned_by_fit(found), line_factor=_number(line.get("factor")),
                   learned_shift_px=learned_shift(found.get("gs_geometry")),
                   line_refuted=line_time_refuted(found.get("line_refits")))


def line_time_refuted(refits) -> bool:
    """Whether the line refit (method_results' line_refits) made a fit started at the learned line-time factor
    and kept the first fit because that one explained the RS image worse: the data do not carry the factor (a
    dim capture with exact timing learned x0.9896 and x0.9845 in two runs and their refits ended 26 % and 10 %
    higher; a capture 2 % long is learned nearly whole where it is: bench/untuned.md, "a line time off, on whole
    runs")."""
    made = refits.get("refits") if isinstance(refits, dict) else None
    if not isinstance(made, list) or refits.get("kept") != 0:
        return False
    worse = [r for r in made if isinstance(r, dict) and _number(r.get("rs")) is not None
             and _number(r.get("from_rs")) is not None and r["rs"] > r["from_rs"]]
    return bool(worse) and len(worse) == len(made)


def above_noise(metrics: dict) -> dict | None:
    """Where a run stopped itself above the noise level (its RS residual over EXPLAINED_RATIO x the noise)
    without a misfit verdict: {"ratio", "line"}, the line saying so, with what the fit tried (the recipe's fit
    stage); else None. A residual there is not noise: something in the RS image is left unexplained."""
    if metrics.get("misfit") or metrics.get("status") != "ok" or metrics.get("ended_by") != "own_stop":
        return None
    found = metrics.get("method_results") or {}
    residual, noise = _number(metrics.get("residual_rs")), _number(found.get("rs_noise_level"))
    if residual is None or noise is None or noise <= 0 or residual / noise <= EXPLAINED_RATIO:
        return None
    ratio = residual / noise
    recipe = found.get("recipe") if isinstance(found.get("recipe"), list) else []
    fit = next((str(r).split("]: ", 1)[-1] for r in recipe if str(r).startswith("stage fit")), None)
    tried = f" after {fit}" if fit else ""
    line = (f"stopped at {ratio:.2f}x the RS noise level{tried} (a fit that explains the data ends below "
            f"{EXPLAINED_RATIO:g}x): part of the RS image is left unexplained")
    key = key_rows_ratio(found.get("self_calibration"), noise)
    if key is not None and key <= KEY_ROWS_EXPLAINED:
        line += (f"; the key rows are explained at {key:.2f}x it, so the PSF, the gains and the GS-to-RS transform are "
                 "consistent: motion between the key frames that the model does not represent")
        if "line time" not in learned_by_fit(found):
            # a line time 2 % or 3 % off leaves a run without the line time learned where an exact one does (1.06-1.43x
            # the noise) and costs it no quality there (bench/untuned.md, "a line time off, on whole runs")
            line += (", or the RS line time (the key rows do not see it and this run did not learn it: "
                     "`rngcam calibrate linetime --flicker` measures it)")
    found_key = {} if key is None else {"key_rows_ratio": key}
    return {"ratio": ratio, "line": line, **found_key}


def learned_shift(geometry) -> float | None:
    """The length (px) of the GS-to-RS shift a fit ended on, on top of the bundle's calibration, from
    method_results' gs_geometry (its "end": self-calibration's start and what the fit learned), or None (not
    learned, or not of rngcam's shape: metrics from elsewhere)."""
    end = geometry.get("end") if isinstance(geometry, dict) else None
    shift = end.get("shift_px") if isinstance(end, dict) else None
    if not (isinstance(shift, list) and len(shift) == 2):
        return None
    dx, dy = (_number(v) for v in shift)
    return None if dx is None or dy is None else math.hypot(dx, dy)
