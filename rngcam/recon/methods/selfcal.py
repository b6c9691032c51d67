"""Self-calibration: the GS/RS gains (and, where the data pin it, the GS-to-RS transform) from the data.

Calibration leaves the GS frames misregistered against the RS image by a fraction of a pixel, a
small rotation and scale (what `calibrate align` leaves; bench/realistic.md), and their
colour gains a few percent off. The RS row bins exposed over (nearly) the same window as a GS
frame see the scene that frame saw; through the PSF they are rows of the GS image taken to RS
coordinates, times the gains (`register_key_rows`). A small least-squares fit of the similarity
and the gains to those rows gives the gains to about a percent; the similarity it suggests is
biased by what the rows and the key frame do not share (motion within the part of the exposures
they do not overlap, the binned forward model's own error), so it is applied only where its
standard error says it is pinned (`calibrate_problem`, mode "all"; bench/realistic.md).
The same rows give the PSF's magnification (a scene at another distance than the
calibration's point source): a one-dimensional search, applied where it lowers their residual
(`calibrate_psf_scale`), made before the registration and again through it (`calibrate_problem`).

Transforms are 3x3 matrices acting on pixel coordinates (x, y) measured from the grid's centre
(pixel centres at i + 0.5 - W / 2), the convention of rngcam.sim.fidelity's truth values.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.methods.key_rows import (  # noqa: F401 - callers import them here
    KEY_ROW_OVERLAP,
    key_row_data,
    key_row_uncertainty,
    key_rows,
)
from rngcam.recon.methods.selfcal_flat import apply_flat, calibrate_flat, flat_lines, held_back


def similarity(dx: float = 0.0, dy: float = 0.0, rotation_rad: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """3x3: p -> scale R(rotation) p + (dx, dy)."""
    c, s = math.cos(rotation_rad) * scale, math.sin(rotation_rad) * scale
    return np.array([[c, -s, dx], [s, c, dy], [0.0, 0.0, 1.0]])


def describe(matrix) -> dict:
    """The shift (px), rotation (degrees) and scale of a similarity matrix."""
    m = np.asarray(matrix, np.float64)
    return {"shift_px": [float(m[0, 2]), float(m[1, 2])],
            "rotation_deg": float(np.degrees(math.atan2(m[1, 0], m[0, 0]))),
            "scale": float(math.hypot(m[0, 0], m[1, 0]))}


def _matrix_t(params: Tensor) -> Tensor:
    """params (dx, dy, rotation, log scale) -> 3x3 (differentiable)."""
    dx, dy, rot, log_s = params
    s = torch.exp(log_s)
    c, n = torch.cos(rot) * s, torch.sin(rot) * s
    zero, one = torch.zeros_like(dx), torch.ones_like(dx)
    return torch.stack([torch.stack([c, -n, dx]), torch.stack([n, c, dy]), torch.stack([zero, zero, one])])


def sample_grid(matrix: Tensor, h: int, w: int) -> Tensor:
    """(1, H, W, 2) grid_sample coordinates (align_corners=False) of M p for every pixel p."""
    dev, dt = matrix.device, matrix.dtype
    ys = torch.arange(h, device=dev, dtype=dt) + 0.5 - h / 2
    xs = torch.arange(w, device=dev, dtype=dt) + 0.5 - w / 2
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    qx = matrix[0, 0] * xx + matrix[0, 1] * yy + matrix[0, 2]
    qy = matrix[1, 0] * xx + matrix[1, 1] * yy + matrix[1, 2]
    return torch.stack([qx * (2.0 / w), qy * (2.0 / h)], dim=-1)[None]


def warp(images: Tensor, matrix: Tensor | np.ndarray) -> Tensor:
    """images (C, N, H, W) sampled at M p (bicubic, border values outside): out(p) = in(M p)."""
    c, n, h, w = images.shape
    m = torch.as_tensor(np.asarray(matrix) if not isinstance(matrix, Tensor) else matrix,
                        dtype=images.dtype, device=images.device)
    grid = sample_grid(m, h, w).expand(n, h, w, 2)
    out = torch.nn.functional.grid_sample(images.transpose(0, 1), grid, mode="bicubic",
                                          padding_mode="border", align_corners=False)
    return out.transpose(0, 1)


# grid_sample's bicubic kernel (Keys' cubic convolution, A = -0.75), which warp_translate reproduces.
_CUBIC_A = -0.75


# The four taps' weights at a fraction t (taps at floor - 1 ... floor + 2), cubic in t: rows times (1, t, t^2, t^3)
_CUBIC_TAPS = ((0.0, _CUBIC_A, -2 * _CUBIC_A, _CUBIC_A), (1.0, 0.0, -(_CUBIC_A + 3), _CUBIC_A + 2),
               (0.0, -_CUBIC_A, 2 * _CUBIC_A + 3, -(_CUBIC_A + 2)), (0.0, 0.0, _CUBIC_A, -_CUBIC_A))


def _cubic_shift_matrix(sizes: tuple[int, ...], shifts: Tensor, dtype, device) -> Tensor:
    """(k, n, n), n = max(sizes): matrix j's top-left (sizes[j], sizes[j]) block samples a line of
    sizes[j] at i + shifts[j] with grid_sample's bicubic taps, clamped to the border (the rest is
    not used). Every row has the same four weights (the shift's fraction, a cubic in it); the matrix
    is them at the 0/1 patterns that pick each row's clamped taps: a few operations for all axes
    whatever n (STFM builds them every step; bench/step_ops.md)."""
    taps, line, base, last = _cubic_constants(tuple(sizes), dtype, torch.device(device))
    s = shifts if shifts.dtype == dtype else shifts.to(dtype)
    whole = s.detach().floor()
    t = (s - whole)[:, None]
    weights = torch.addcmul(taps[2], taps[3], t)  # Horner: the taps' cubics at t, (k, 4)
    weights = torch.addcmul(taps[1], weights, t)
    weights = torch.addcmul(taps[0], weights, t)
    picks = (torch.minimum(base + whole.long()[:, None, None], last).clamp_(min=0)[..., None] == line).to(dtype)
    n = line.shape[0]
    return torch.bmm(weights[:, None], picks.view(len(sizes), 4, n * n)).view(len(sizes), n, n)


@functools.lru_cache(maxsize=32)
def _cubic_constants(sizes: tuple[int, ...], dtype, device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(_CUBIC_TAPS by power (4 powers, 4 taps), the line's indices (n,), each tap's line index
    unclamped (4, n), each axis's last index (k, 1, 1)) on `device`."""
    line = torch.arange(max(sizes), device=device)
    last = torch.tensor(sizes, device=device)[:, None, None] - 1
    return (torch.tensor(_CUBIC_TAPS, dtype=dtype, device=device).T.contiguous(), line,
            line + torch.arange(-1, 3, device=device)[:, None], last)


def warp_translate(images: Tensor, shift: Tensor) -> Tensor:
    """`warp` by a translation shift (2,) = (dx, dy) (out(p) = in(p + (dx, dy)), bicubic, border values
    outside), as one small matrix product per axis: the same values in less than grid_sample's time with
    its backward on a CPU (bench/convergence.md). A gradient reaches `shift`."""
    c, n, h, w = images.shape
    cols, rows = _cubic_shift_matrix((w, h), shift, images.dtype, images.device).unbind(0)
    if h != w:
        cols, rows = cols[:w, :w], rows[:h, :h]
    # mm and bmm on the matrices as matmul takes them (the same products, without its broadcasting views)
    along_x = torch.mm(images.reshape(c * n * h, w), cols.transpose(0, 1)).view(c * n, h, w)
    return torch.bmm(rows.expand(c * n, h, h), along_x).view(c, n, h, w)


def inside(matrix: Tensor, h: int, w: int) -> Tensor:
    """(H, W): 1 where M p lies within the grid's outer pixel centres (warp samples no border value there), else 0."""
    g = sample_grid(matrix.detach(), h, w)[0]
    return ((g[..., 0].abs() <= 1 - 1 / w + 1e-4) & (g[..., 1].abs() <= 1 - 1 / h + 1e-4)).to(matrix.dtype)


def pose_matrix(pose: Tensor, radius: float) -> Tensor:
    """3x3 (differentiable) of a pose (dx, dy px; rotation, log scale, each times `radius` px):
    all four in pixels of displacement at `radius` from the centre, so one step size suits them."""
    return _matrix_t(torch.stack([pose[0], pose[1], pose[2] / radius, pose[3] / radius]))


def is_identity(matrix, tol: float = 1e-9) -> bool:
    return bool(np.allclose(np.asarray(matrix), np.eye(3), atol=tol))


# ----------------------------------------------------------------------------- key rows (rngcam.recon.methods.key_rows)

def register_key_rows(problem, iters: int = 30, free: int = 4) -> dict | None:
    """GS-to-RS similarity S and GS/RS gains from the RS rows exposed with a GS frame.

    Such a row sees the scene the GS frame saw (over the same window): through the PSF, it is row
    r of the GS image taken to RS coordinates (sampled at S^-1), times the gains, times its
    exposure. Fitting S^-1 (`free` of shift x, y, rotation, log scale) and the gains to those rows
    is a small least-squares problem, independent of how anything moves between key frames.
    Returns {"matrix": S (3x3), "gains": (C,), "rs_residual_before"/"after": relative, "rows": n}
    or None without such rows."""
    data = key_row_data(problem)
    if data is None:
        return None
    p, images, valid, rowsum, sel, targets = data
    c = images.shape[0]
    conv = p.rs_op().conv
    norm = float(sum(t.square().sum() for t in targets).clamp_min(1e-30))
    dev = images.device
    gain0 = (torch.ones(c, dtype=torch.float64) if p.white_balance is None else p.white_balance.double()).to(dev)
    params = torch.zeros(free, dtype=torch.float64, device=dev, requires_grad=True)
    log_gain = torch.log(gain0.clone()).requires_grad_(True)

    def misses(prm: Tensor, lg: Tensor) -> Tensor:
        """The weighted residual vector over the key rows, / sqrt(norm)."""
        m = _matrix_t(torch.cat([prm, torch.zeros(4 - free, dtype=prm.dtype, device=prm.device)]))
        out = []
        for (g, rows), target in zip(sel, targets, strict=True):
            img = warp(images[:, g:g + 1], m)[:, 0] * torch.exp(lg)[:, None, None]
            pred = conv.A(img)[:, rows] * rowsum[rows][None, :, None]
            if valid is not None:
                pred = pred * valid[:, rows]
            out.append((pred - target).flatten())
        return torch.cat(out) / math.sqrt(norm)

    def misfit() -> Tensor:
        return misses(params, log_gain).square().sum()

    with torch.no_grad():
        start = float(misfit())
    opt = torch.optim.LBFGS([params, log_gain], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-15)

    def closure():
        opt.zero_grad()
        loss = misfit()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        end = float(misfit())
    sigma = key_row_uncertainty(misses, params.detach(), log_gain.detach())
    rows_used = int(sum(len(r) for _, r in sel))
    if not (math.isfinite(end) and end < start):
        return {"matrix": np.eye(3), "gains": gain0.cpu().numpy(), "rs_residual_before": math.sqrt(start),
                "rs_residual_after": math.sqrt(start), "rows": rows_used, "sigma": sigma}
    fixed = torch.zeros(4 - free, dtype=params.dtype, device=params.device)
    inv = _matrix_t(torch.cat([params.detach(), fixed])).cpu().numpy()
    return {"matrix": np.linalg.inv(inv), "gains": torch.exp(log_gain.detach()).cpu().numpy(),
            "rs_residual_before": math.sqrt(start), "rs_residual_after": math.sqrt(end), "rows": rows_used,
            "sigma": sigma}


# ----------------------------------------------------------------------------- the problem

MODES = ("off", "gains", "all")  # what calibrate_problem applies (all: gains, the GS-to-RS transform, the flat errors)
MAX_SIGMA_PX = 0.1  # a transform whose shift is less certain than this is not applied
MAX_ROTATION_DEG, MAX_SCALE = 2.0, 0.03  # beyond these the key rows fitted something else


def calibrate_problem(problem, mode: str = "gains", psf_scale: bool = True, flat: bool = True):
    """(problem with its GS frames on the RS scale and in RS coordinates, report) from the key
    rows (register_key_rows): b_gs becomes gains x b_gs sampled at S^-1 (white balance then 1).
    The report has the start values (identity, the bundle's white balance), the refined ones,
    their standard errors, and why a transform was not applied; with `psf_scale`, then the PSF's
    magnification (calibrate_psf_scale: report["scales"]["psf"]); with `flat`, the PSF's background and
    the GS vignetting (rngcam.recon.methods.selfcal_flat: report["flat"]), applied in mode "all" only
    (bench/realistic.md, "the PSF's background and GS vignetting self-calibrated").

    The PSF scale is searched first with the GS frames as they are: a registration through a PSF
    some percent off takes up its error as rotation and scale, and a search through that registration
    stops short (bench/realistic.md, "The PSF scale searched before the registration"). The transform
    is then fitted through the PSF so magnified, the scale searched again through it, and the gains
    and transform fitted once more through the PSF and GS frames the fit will use (through the PSF as
    handed the gains absorb its error). mode "off": (problem, None)."""
    if mode not in MODES:
        raise ConfigError(f"self_calibrate must be one of {', '.join(MODES)}, got {mode!r}")
    if mode == "off" or problem.b_rs is None or problem.b_gs is None:
        return problem, None
    first = calibrate_psf_scale(problem)[1] if psf_scale else None
    through = problem  # registered through the PSF the first search found (a shrink too: it is reported)
    if first is not None and first["fits"]:
        through = replace(problem, psf=_magnified(problem.psf, first["estimate"]), notes=list(problem.notes))
    found = _register(through, mode)
    if found is None:
        return problem, {"mode": mode, "applied": False,
                         "why": "no RS row is exposed over the same window as a GS frame"}
    report, matrix, fitted = found
    calibrated = _apply(problem, matrix, np.asarray(report["refined"]["gains"], np.float64))
    # the key rows' transform where it was not applied to the GS frames (it steadies the searches)
    held = fitted if "transform_rejected" in report else None
    found = {}
    if psf_scale:
        calibrated, scale = calibrate_psf_scale(calibrated, held)
        if scale is not None:
            scale["first_estimate"] = None if first is None else first["estimate"]
            found["scales"] = {"psf": scale}
    if flat:  # the PSF's background and the GS vignetting (selfcal_flat), through the PSF so magnified
        found["flat"] = calibrate_flat(calibrated)
        if mode != "all":
            found["flat"] = held_back(found["flat"], f"self_calibrate={mode} (mode all applies it)")
    final = apply_flat(replace(problem, psf=calibrated.psf, notes=list(problem.notes)), found.get("flat"))
    if final.psf is not through.psf or final.b_gs is not problem.b_gs:
        again = _register(final, mode)  # the gains and transform through the PSF and GS frames the fit will use
        if again is not None:
            report, matrix, _ = again
            calibrated = _apply(final, matrix, np.asarray(report["refined"]["gains"], np.float64))
    return calibrated, {**report, **found}


def _magnified(psf: Tensor, scale: float) -> Tensor:
    """The PSF magnified by `scale` about its centre (rngcam.physics.psf.magnify), in its dtype."""
    from rngcam.physics.psf import magnify  # heavy: psf loads cv2

    return torch.from_numpy(magnify(psf.double().cpu().numpy(), scale)).to(psf.dtype)


def _register(problem, mode: str) -> tuple[dict, np.ndarray, np.ndarray] | None:
    """(report, the transform to apply, the transform fitted) of the key-row fit of the gains and the
    transform (None without key rows); the one to apply is the identity where `mode` or its
    uncertainty keeps the fitted one out."""
    c = problem.channels
    wb0 = np.ones(c) if problem.white_balance is None else problem.white_balance.double().cpu().numpy()
    # The transform is always fitted: left out, a misregistration biases the gains by several percent.
    result = register_key_rows(problem, free=4)
    if result is None:
        return None
    why = None
    d = describe(result["matrix"])
    sig = result["sigma"]
    if mode == "gains":
        why = "self_calibrate=gains"
    elif max(sig.get("shift_x_px", 0), sig.get("shift_y_px", 0)) > MAX_SIGMA_PX:
        why = f"shift uncertain (standard error > {MAX_SIGMA_PX} px)"
    elif abs(d["rotation_deg"]) > MAX_ROTATION_DEG or abs(d["scale"] - 1) > MAX_SCALE:
        why = f"rotation {d['rotation_deg']:.2f} deg / scale {d['scale']:.4f} beyond what calibration leaves"
    gains = np.asarray(result["gains"], np.float64)
    report = {"mode": mode, "applied": True, "rows": result["rows"],
              "rs_residual_before": result["rs_residual_before"], "rs_residual_after": result["rs_residual_after"],
              "start": {**describe(np.eye(3)), "gains": wb0.tolist()},
              "refined": {**describe(result["matrix"]), "gains": gains.tolist()},
              "sigma": result["sigma"],  # the misfit verdict reads the shift's where the transform is plausible
              "transform_plausible": bool(abs(d["rotation_deg"]) <= MAX_ROTATION_DEG
                                          and abs(d["scale"] - 1) <= MAX_SCALE)}
    if why is not None:
        report["transform_not_applied"] = why
        report["transform_rejected"] = report["refined"]
        report["refined"] = {**describe(np.eye(3)), "gains": gains.tolist()}
    return report, (np.eye(3) if why is not None else result["matrix"]), result["matrix"]


def _apply(problem, matrix: np.ndarray, gains: np.ndarray):
    """The problem with b_gs := gains * b_gs sampled at S^-1 (valid pixels likewise), white balance 1."""
    b_gs = problem.b_gs
    inv = np.linalg.inv(matrix)
    gs_valid = problem.gs_valid
    if not is_identity(matrix):
        b_gs = warp(b_gs, inv)
        if gs_valid is not None:
            moved = warp(gs_valid.to(b_gs.dtype).expand(b_gs.shape[0], *gs_valid.shape[1:]), inv)
            gs_valid = moved > 1 - 1e-6
    g = torch.as_tensor(gains, dtype=b_gs.dtype, device=b_gs.device)
    return replace(problem, b_gs=b_gs * g[:, None, None, None], gs_valid=gs_valid,
                   white_balance=torch.ones_like(g), notes=list(problem.notes))


def report_lines(report: dict | None, end_gains=None) -> list[str]:
    """One note per refined value: start -> refined (-> end for the gains a fit learned further)."""
    if not report:
        return []
    if not report.get("applied"):
        return [f"self-calibration ({report['mode']}) not applied: {report['why']}"]
    s, r = report["start"], report["refined"]
    through = f" through {report['through']}" if isinstance(report.get("through"), str) else ""
    lines = [f"self-calibration ({report['mode']}){through} from {report['rows']} RS rows exposed with the GS frames: "
             f"RS residual on them {report['rs_residual_before']:.4f} -> {report['rs_residual_after']:.4f}"]
    if "transform_not_applied" not in report:
        lines.append(f"GS-to-RS shift ({s['shift_px'][0]:+.3f}, {s['shift_px'][1]:+.3f}) -> "
                     f"({r['shift_px'][0]:+.3f}, {r['shift_px'][1]:+.3f}) px, rotation {s['rotation_deg']:+.3f} -> "
                     f"{r['rotation_deg']:+.3f} deg, scale {s['scale']:.4f} -> {r['scale']:.4f}")
    if "transform_not_applied" in report:
        x = report["transform_rejected"]
        lines.append(f"GS-to-RS transform kept ({report['transform_not_applied']}); the key rows suggested shift "
                     f"({x['shift_px'][0]:+.3f}, {x['shift_px'][1]:+.3f}) px, rotation {x['rotation_deg']:+.3f} deg, "
                     f"scale {x['scale']:.4f}")
    psf = (report.get("scales") or {}).get("psf")
    if psf:
        outcome = "applied" if psf["applied"] else f"not applied, {psf['why']}"
        first = "" if psf.get("first_estimate") is None else f"; x{psf['first_estimate']:.4f} before registering"
        lines.append(f"PSF scale {psf['estimate']:.4f} estimated from the key rows (residual "
                     f"{psf['residual_before']:.4f} -> {psf['residual_after']:.4f}{first}): {outcome}")
    lines += flat_lines(report.get("flat"))
    gains = "/".join(f"{g:.3f}" for g in s["gains"]) + " -> " + "/".join(f"{g:.3f}" for g in r["gains"])
    if end_gains is not None:
        gains += " -> " + "/".join(f"{g * r0:.3f}" for g, r0 in zip(end_gains, r["gains"], strict=True)) + " (fit)"
    if psf and psf["applied"]:
        gains += f" (fitted through the PSF magnified x{psf['end']:.4f})"
    lines.append(f"GS/RS gains {gains}")
    return lines


# ----------------------------------------------------------------------------- PSF scale

PSF_SCALE_RANGE = (0.90, 1.10)  # the magnifications searched (a scene nearer or further than the calibration's)
MIN_DROP = 0.03  # a scale is applied when it lowers the key rows' residual by at least this share
_COARSE, _FINE = 0.02, 0.005  # search steps
# A PSF measured too large (the point source nearer than the scene) lost its outer ring off the
# sensor; shrunk, it lacks that edge. Applied, such shrinks lowered the RS residual and the video's
# PSNR alike (the clip, PSF 5 % large; bench/realistic.md, "The PSF scale searched before the registration").
SHRINK_WHY = "a PSF shrunk on the grid lacks the edge its measurement lost: measure the PSF at the scene's distance"
# Magnifying the grid PSF resamples a caustic that is sharp at the grid's pixels: each candidate
# mixes neighbouring pixels by its sub-pixel phases, the unmagnified one not at all, and that
# blur alone would pull the search to 1. The search compares candidates all blurred to this
# spread (pixels^2 per axis; rngcam.physics.psf.even_blur).
EVEN_BLUR = 0.25


def key_row_misfit(problem, matrix=None):
    """A function psf (C or 1, Hp, Wp) -> (the key rows' relative residual, the GS/RS gains (C,))
    with that PSF, the gains fitted in closed form, the GS frames taken to RS coordinates by
    `matrix` (3x3, GS-to-RS; identity by default); None without key rows."""
    data = key_row_data(problem)
    if data is None:
        return None
    p, images, valid, rowsum, sel, targets = data
    if matrix is not None and not is_identity(matrix):
        images = warp(images, np.linalg.inv(np.asarray(matrix, np.float64)))
    norm = float(sum(t.square().sum() for t in targets).clamp_min(1e-30))

    def misfit(psf) -> tuple[float, np.ndarray]:
        conv = replace(p, psf=torch.as_tensor(psf, dtype=torch.float64)).rs_op().conv
        num = torch.zeros(images.shape[0], dtype=torch.float64)
        den = torch.zeros_like(num)
        for (g, rows), target in zip(sel, targets, strict=True):
            pred = conv.A(images[:, g])[:, rows] * rowsum[rows][None, :, None]
            if valid is not None:
                pred = pred * valid[:, rows]
            num += (pred * target).sum((1, 2)).cpu()
            den += pred.square().sum((1, 2)).cpu()
        den = den.clamp_min(1e-30)
        left = max(norm - float((num.square() / den).sum()), 0.0)
        return math.sqrt(left / norm), (num / den).numpy()

    return misfit


def _parabola(xs: np.ndarray, ys: np.ndarray) -> float:
    """The vertex of the parabola through the lowest point and its neighbours (the lowest point
    itself at an end of the range or where the three do not curve upwards)."""
    i = int(np.argmin(ys))
    if i == 0 or i == len(xs) - 1:
        return float(xs[i])
    (x0, x1, x2), (y0, y1, y2) = xs[i - 1:i + 2], ys[i - 1:i + 2]
    denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denom
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / denom
    return float(xs[i]) if a <= 0 else float(np.clip(-b / (2 * a), x0, x2))


def line_search(at, lo: float, hi: float, coarse: float, fine: float, width: float, include=()) -> float:
    """The x in [lo, hi] where at(x) is lowest: a grid of step `coarse` (and the points `include`),
    one of step `fine` within `width` of its best, and the vertex of the parabola through the lowest
    three of that (its best sample where the vertex is no better). Non-finite values count as worst."""
    xs = np.unique(np.append(np.arange(lo, hi + 1e-9, coarse), include))
    ys = np.nan_to_num(np.array([at(x) for x in xs]), nan=np.inf)
    best = float(xs[int(np.argmin(ys))])
    xf = np.arange(max(lo, best - width), min(hi, best + width) + 1e-9, fine)
    yf = np.nan_to_num(np.array([at(x) for x in xf]), nan=np.inf)
    estimate = _parabola(xf, yf)
    if at(estimate) > float(yf.min()):  # the parabola missed: the best point sampled
        estimate = float(xf[int(np.argmin(yf))])
    return estimate


def estimate_psf_scale(problem, matrix=None, scales: tuple[float, float] = PSF_SCALE_RANGE) -> dict | None:
    """The magnification s of the problem's PSF (about its centre: rngcam.physics.psf.magnify) that
    best explains the key rows: a coarse search over `scales`, a finer one around the best, and a
    parabola through the lowest three, candidates compared at one blur (EVEN_BLUR). Returns
    {"estimate", "residual_before" (the PSF as it is), "residual_after" (magnified by the
    estimate), "at_bound"} or None without key rows."""
    from rngcam.physics.psf import magnify  # heavy: psf loads cv2

    misfit = key_row_misfit(problem, matrix)
    if misfit is None:
        return None
    psf = problem.psf.double().cpu().numpy()

    def at(s: float) -> float:  # every candidate blurred alike, the unmagnified one too
        return misfit(magnify(psf, s, blur=EVEN_BLUR))[0]

    lo, hi = scales
    estimate = line_search(at, lo, hi, _COARSE, _FINE, 2 * _COARSE, include=(1.0,))
    return {"estimate": estimate, "residual_before": misfit(psf)[0],
            "residual_after": misfit(magnify(psf, estimate))[0],
            "at_bound": bool(min(estimate - lo, hi - estimate) < _FINE / 2)}


def calibrate_psf_scale(problem, matrix=None, min_drop: float = MIN_DROP):
    """(problem, report): the PSF magnified by estimate_psf_scale's estimate where that lowers the
    key rows' residual by at least `min_drop` (and is not at the search's bound); report
    {"start": 1, "estimate", "residual_before", "residual_after", "fits" (it lowers the residual by
    min_drop, within the search's bounds), "applied", "end" (the scale the fit uses), "why" (where not
    applied)} (None without key rows). A scale below 1 that fits is reported, never applied
    (SHRINK_WHY)."""
    found = estimate_psf_scale(problem, matrix)
    if found is None:
        return problem, None
    drop = 1 - found["residual_after"] / max(found["residual_before"], 1e-30)
    report = {"start": 1.0, **found, "fits": False, "applied": False, "end": 1.0}
    if not (math.isfinite(drop) and math.isfinite(found["estimate"])):
        report["why"] = "the key rows' residual is not finite"
    elif found["at_bound"]:
        report["why"] = f"at the search's bound ({PSF_SCALE_RANGE[0]:g}-{PSF_SCALE_RANGE[1]:g})"
    elif drop < min_drop:
        report["why"] = (f"the key rows' residual fell by {100 * drop:.1f} % (< {100 * min_drop:g} %)" if drop > 0 else
                         "the magnified PSF (resampled on the grid) does not lower the key rows' residual")
    elif found["estimate"] < 1:
        report["fits"], report["why"] = True, SHRINK_WHY
    else:
        report["fits"] = report["applied"] = True
        report["end"] = found["estimate"]
        problem = replace(problem, psf=_magnified(problem.psf, found["estimate"]), notes=list(problem.notes))
    return problem, report
