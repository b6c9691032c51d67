"""The two flat errors no calibration measures, self-calibrated from the key rows: the PSF's residual
background and the GS frames' vignetting.

`calibrate psf` subtracts a dark frame; what it leaves is a background flat over the PSF's frame, a
share b of its sum (0.1 % of a diffuser caustic's peak is 1.5 % of its sum). Through the PSF it adds b x a
box-filtered scene to every RS pixel, and the PSF's own far field cannot show it: a caustic that fills the
sensor has no dark region (the packaged one's faintest pixel is 0.8 % of its peak). The GS lens darkens its
frames' corners by a share a (GS = scene x (1 - a r^2), r relative to the half diagonal); nothing measures it.

The key rows (rngcam.recon.methods.key_rows) see the scene the GS frames saw through the PSF; with both
errors their prediction is, per channel c,

    g_c (A_H(img) - b A_T(img) + a A_H(img r^2)),

A_H the key rows' operator through the PSF, A_T through a flat PSF summing to 1, linear in the gains g_c
given (b, a). A Gauss-Newton fit of the gains and one b and a shared by the channels gives both with
standard errors (sigma^2 (J^T J)^-1, sigma^2 from the residual). Each is applied only where it lowers the
key rows' residual by more than noise would (|estimate| >= MIN_Z standard errors: the residual's drop is
z^2 sigma^2) and lies within what a dark frame or a lens leaves, and then only its lower confidence bound,
estimate - MIN_Z standard errors: what the key rows pin. An estimate that clears the threshold is one that
noise, or scene content a flat term also fits, pushed up; the bound over-corrects only where the estimate
lies more than MIN_Z standard errors above the truth (bench/realistic.md, "the PSF's background and GS
vignetting self-calibrated"). The gains are then fitted again through the corrected data
(rngcam.recon.methods.selfcal.calibrate_problem). Self-calibration applies them in its mode "all" only;
its default reports them (`held_back`): on the captures measured they won nothing, and a PSF without its
background lost a fit its ball (the same bench section).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.methods.key_rows import key_row_data

MIN_Z = 2.0  # the background is applied where it is at least this many standard errors from 0
# The vignetting's estimate strays further than its standard error says (scene content that a radial
# falloff also fits: bench/realistic.md)
MIN_Z_VIGNETTING = 3.0
MAX_BACKGROUND = 0.10  # of the PSF's sum: beyond it the key rows fitted something else
MAX_VIGNETTING = 0.20  # falloff at the corners
_STEPS = 8  # Gauss-Newton steps
_MAX_CONDITION = 1e12  # of the normal matrix (columns scaled to 1): beyond it a value is not determined


def radius2(h: int, w: int, dtype=torch.float64, device="cpu") -> Tensor:
    """(H, W) squared distance of each pixel centre from the grid's centre, relative to the half
    diagonal (rngcam.sim.fidelity.vignetting_field's r^2)."""
    ys = torch.arange(h, dtype=dtype, device=device) + 0.5 - h / 2
    xs = torch.arange(w, dtype=dtype, device=device) + 0.5 - w / 2
    return (ys[:, None] ** 2 + xs[None, :] ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)


def without_background(psf: Tensor, share: float) -> Tensor:
    """The PSF (C or 1, Hp, Wp) less a flat background of `share` of each channel's sum, clamped at 0
    and normalised to sum 1 per channel again (ConfigError where nothing positive is left)."""
    p = psf.double()
    sums = p.sum((-2, -1), keepdim=True)
    if not (bool(torch.isfinite(p).all()) and bool((sums > 0).all())):
        raise ConfigError("the PSF has no positive signal (or is not finite): no background to subtract")
    flat = sums * (float(share) / (p.shape[-2] * p.shape[-1]))
    out = (p - flat).clamp_min(0)
    left = out.sum((-2, -1), keepdim=True)
    if not bool((left > 0).all()):
        raise ConfigError(f"subtracting a background of {100 * share:.1f} % of the PSF's sum leaves nothing")
    return (out / left).to(psf.dtype)


def devignetted(b_gs: Tensor, amount: float) -> Tensor:
    """GS frames (C, G, H, W) divided by the falloff 1 - amount r^2."""
    h, w = b_gs.shape[-2:]
    return b_gs / (1 - amount * radius2(h, w, b_gs.dtype, b_gs.device))


def _columns(problem):
    """Per channel, the key rows' measured values and three predictions (through the PSF, through a
    flat PSF, through the PSF of the GS images times r^2), each (C, n); None without key rows."""
    data = key_row_data(problem)
    if data is None:
        return None
    p, images, valid, rowsum, sel, targets = data
    c, _, h, w = images.shape
    conv = p.rs_op().conv
    flat = replace(p, psf=torch.ones_like(p.psf) / (p.psf.shape[-2] * p.psf.shape[-1])).rs_op().conv
    r2 = radius2(h, w, images.dtype, images.device)
    cols: dict[str, list[Tensor]] = {"t": [], "H": [], "T": [], "V": []}
    for (g, rows), target in zip(sel, targets, strict=True):
        mask = 1 if valid is None else valid[:, rows]
        for key, op, img in (("H", conv, images[:, g]), ("T", flat, images[:, g]), ("V", conv, images[:, g] * r2)):
            cols[key].append((op.A(img)[:, rows] * rowsum[rows][None, :, None] * mask).reshape(c, -1))
        cols["t"].append(target.reshape(c, -1))
    return {k: torch.cat(v, 1).cpu() for k, v in cols.items()}, int(sum(len(r) for _, r in sel))


def _gauss_newton(t: Tensor, hh: Tensor, extras: list[Tensor]) -> tuple[np.ndarray, np.ndarray, float, float] | str:
    """Fit g_c (hh + sum_k theta_k extras_k) to t (each (C, n)): (theta, its standard errors, the relative
    residual at theta = 0 and at theta), the gains g_c (one per channel) fitted alongside; or why the
    data cannot give them (no light, nothing finite, the extras indistinguishable from the PSF)."""
    c, k = t.shape[0], len(extras)
    norm = float(t.square().sum())
    if not (math.isfinite(norm) and norm > 0 and bool(torch.isfinite(hh).all())):
        return "the key rows hold no light (or are not finite)"

    def prediction(theta: Tensor) -> Tensor:
        return hh + sum(th * x for th, x in zip(theta, extras, strict=True))

    def residual(x: Tensor) -> Tensor:  # x = (g_1..g_C, theta_1..theta_k)
        return (x[:c, None] * prediction(x[c:]) - t).flatten()

    def jacobian(x: Tensor) -> Tensor:  # (C n, C + k)
        pred, n = prediction(x[c:]), t.shape[1]
        jg = torch.zeros(c, n, c, dtype=t.dtype)
        jg[torch.arange(c), :, torch.arange(c)] = pred
        return torch.cat([jg.reshape(c * n, c)] + [(x[:c, None] * e).reshape(-1, 1) for e in extras], dim=1)

    gains = (hh * t).sum(1) / hh.square().sum(1).clamp_min(1e-300)
    x = torch.cat([gains, torch.zeros(k, dtype=t.dtype)])
    start = float(residual(x).square().sum())
    for _ in range(_STEPS):  # bilinear: two or three steps reach the minimum
        step = torch.linalg.lstsq(jacobian(x), -residual(x)[:, None]).solution[:, 0]
        if not bool(torch.isfinite(step).all()):
            break
        x = x + step
    r = residual(x)
    if not (bool(torch.isfinite(x).all()) and bool(torch.isfinite(r).all())):
        return "the fit did not converge"
    jac = jacobian(x)
    scale = jac.norm(dim=0).clamp_min(1e-300)  # columns of very different sizes: condition the normal matrix
    normal = (jac / scale).T @ (jac / scale)
    if not float(torch.linalg.cond(normal)) < _MAX_CONDITION:
        return "the key rows cannot tell it from the PSF and the gains (a scene too plain)"
    cov = torch.linalg.inv(normal) / (scale[:, None] * scale[None, :]) * float(r.square().sum()) \
        / max(r.numel() - x.numel(), 1)
    sigma = cov.diagonal()[c:].clamp_min(0).sqrt().numpy()
    return x[c:].numpy(), sigma, math.sqrt(start / norm), math.sqrt(float(r.square().sum()) / norm)


def estimate_flat(problem) -> dict | None:
    """The PSF's background (share of its sum) and the GS vignetting (falloff at the corners) the key
    rows suggest, with standard errors: {"background", "background_sigma" (fitted alone with the gains),
    "vignetting", "vignetting_sigma", "background_with", "background_with_sigma" (fitted with the
    vignetting), "residual_before" (neither), "residual_after" (background alone), "residual_both",
    "rows"} ({"rows", "why"} where the key rows cannot give them); None without key rows. The GS frames
    are taken as they are (the transform self-calibration applied, not the one the key rows suggest: on
    their few rows that can be far off, a rotation of degrees)."""
    found = _columns(problem)
    if found is None:
        return None
    cols, rows = found
    alone = _gauss_newton(cols["t"], cols["H"], [-cols["T"]])
    both = _gauss_newton(cols["t"], cols["H"], [-cols["T"], cols["V"]])
    for fit in (alone, both):
        if isinstance(fit, str):
            return {"rows": rows, "why": fit}
    (b,), (sb,), before, after = alone
    (bw, a), (sbw, sa), _, both = both
    return {"background": float(b), "background_sigma": float(sb), "vignetting": float(a),
            "vignetting_sigma": float(sa), "background_with": float(bw), "background_with_sigma": float(sbw),
            "residual_before": before, "residual_after": after, "residual_both": both, "rows": rows}


def _decide(value: float, sigma: float, min_z: float, bound: float) -> str | None:
    """Why an estimate is not applied (None where it is): it must lie in (0, bound] and `min_z`
    standard errors from 0."""
    if not (math.isfinite(value) and math.isfinite(sigma)):
        return "not finite"
    if value <= 0:
        return "not positive (neither a dark frame's subtraction nor a lens adds light there)"
    if value < min_z * sigma:
        return f"within {min_z:g} standard errors of 0 (the key rows do not pin it)"
    if value > bound:
        return f"beyond {100 * bound:g} % (the key rows fitted something else)"
    return None


def calibrate_flat(problem) -> dict | None:
    """{"rows", "residual_before", "residual_after", "background": {...}, "vignetting": {...}}, each
    of the last two {"estimate", "sigma", "applied", "value" (applied: the estimate less its threshold's
    standard errors) or "why" (not applied)} ({"rows", "why"} where the key rows cannot give them); None
    without key rows. The vignetting is fitted with the background and applied where it is
    MIN_Z_VIGNETTING standard errors from 0; the background is fitted with it where it is applied, alone
    (more precisely) where not. Apply the report with `apply_flat`."""
    found = estimate_flat(problem)
    if found is None or "why" in found:
        return found
    a, sa = found["vignetting"], found["vignetting_sigma"]
    why_a = _decide(a, sa, MIN_Z_VIGNETTING, MAX_VIGNETTING)
    with_a = why_a is None
    b, sb = (found["background_with"], found["background_with_sigma"]) if with_a else \
        (found["background"], found["background_sigma"])
    why_b = _decide(b, sb, MIN_Z, MAX_BACKGROUND)
    out = {"rows": found["rows"], "residual_before": found["residual_before"],
           "residual_after": found["residual_both"] if with_a else found["residual_after"]}
    for key, value, sigma, why, z in (("background", b, sb, why_b, MIN_Z),
                                      ("vignetting", a, sa, why_a, MIN_Z_VIGNETTING)):
        out[key] = {"estimate": value, "sigma": sigma, "applied": why is None}
        if why is None:
            out[key]["value"] = value - z * sigma  # the lower confidence bound: what the key rows pin
        else:
            out[key]["why"] = why
    return out


def held_back(report: dict | None, why: str) -> dict | None:
    """`report` (calibrate_flat's) with nothing applied: what it would apply kept as "would_apply", with
    `why` it is not."""
    if not report or "why" in report:
        return report
    out = dict(report)
    for key in ("background", "vignetting"):
        r = {k: v for k, v in report[key].items() if k != "value"}
        if r["applied"]:
            r.update(applied=False, would_apply=report[key]["value"], why=why)
        out[key] = r
    return out


def apply_flat(problem, report: dict | None):
    """The problem with what `report` (calibrate_flat's) applies: the PSF less its background, the GS
    frames divided by their falloff; the same problem where it applies nothing."""
    if not report or "why" in report:
        return problem
    changes = {}
    if report["background"]["applied"]:
        changes["psf"] = without_background(problem.psf, report["background"]["value"])
    if report["vignetting"]["applied"] and problem.b_gs is not None:
        changes["b_gs"] = devignetted(problem.b_gs, report["vignetting"]["value"])
    return replace(problem, **changes, notes=list(problem.notes)) if changes else problem


def flat_lines(report: dict | None) -> list[str]:
    """One note per flat error: the estimate, its standard error and what of it was applied."""
    if not report:
        return []
    if "why" in report:
        return [f"PSF background and GS vignetting not estimated: {report['why']}"]
    lines = []
    for key, what in (("background", "PSF background"), ("vignetting", "GS vignetting")):
        r = report[key]
        if r["applied"]:
            outcome = f"{100 * r['value']:.2f} % applied (its lower confidence bound)"
        elif "would_apply" in r:
            outcome = f"{100 * r['would_apply']:.2f} % (its lower confidence bound) not applied, {r['why']}"
        else:
            outcome = f"not applied, {r['why']}"
        where = "of the PSF's sum" if key == "background" else "at the corners"
        lines.append(f"{what} {100 * r['estimate']:+.2f} % +/- {100 * r['sigma']:.2f} % ({where}) "
                     f"estimated from the key rows: {outcome}")
    return lines
