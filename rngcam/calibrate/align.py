"""GS-to-RS alignment and white balance from one static scene seen by both cameras.

Convention (the bundle's, rngcam.recon.problem): `gs_to_rs` is a 3x3 homography mapping a raw
GS pixel (x, y, 1) to the raw RS sensor pixel that sees the same scene point; pixel centres
are at integer coordinates. `white_balance[c]` multiplies GS measurements (operator units) to
put them on the RS scale: it is the recon's Lambda in ||A_G v - Lambda b_G||^2, i.e. RS
response / GS response per channel (1 / GS gain when the RS camera is the reference).

Steps, all on a working grid (the RS image binned so its long side is at most `max_side`):
1. Deconvolve the RS image (rngcam.calibrate.deconv: Wiener, then monotone FISTA-TV).
2. Initial transform: the given one (the rig's), or SIFT feature matches between the GS image
   and the deconvolved RS image with RANSAC when they give enough inliers (the better of the
   two by ECC correlation wins).
3. OpenCV ECC (affine or homography, coarse to fine) between the deconvolved RS image and the
   GS image warped onto the RS grid; a similarity model keeps the best-fit similarity.
4. Refinement in the measurement domain: the transform's parameters are fitted by least
   squares so that Lambda * (e_RS / e_GS) * (PSF conv warped GS) matches the raw RS image,
   with the per-channel Lambda solved in closed form at every step. This uses every RS pixel
   and none of the deconvolution's bias; it needs the target on a dark background inside both
   fields of view (light the GS camera misses would otherwise reach the RS sensor).
5. Residual: local shifts (phase correlation on tiles) between the deconvolved RS image and
   the GS image warped with the final transform; their median, in RS sensor pixels, is
   reported (it includes the deconvolution's own errors, so it bounds the misregistration
   from above), with the refined transform's 1-sigma uncertainty from the fit's covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from rngcam.calibrate.deconv import deconvolve, few_threads
from rngcam.errors import RngcamError
from rngcam.physics.geometry import apply_homography, fit_similarity, grid_points, similarity_matrix
from rngcam.physics.operators import PSFConvolution
from rngcam.physics.psf import normalise, resample

MODELS = ("similarity", "homography")
MIN_FEATURE_INLIERS = 8
OUTSIDE_LIGHT_WARN = 0.02  # fraction of RS light the GS camera does not see


class AlignmentError(RngcamError):
    """The static pair cannot be aligned (no texture, no overlap, no convergence)."""


# --------------------------------------------------------------------------- working grids


def bin_matrix(factor: int) -> np.ndarray:
    """Raw pixel coordinates -> coordinates after `factor` x `factor` binning (pixel centres)."""
    a = 1.0 / factor
    return np.array([[a, 0, 0.5 * a - 0.5], [0, a, 0.5 * a - 0.5], [0, 0, 1.0]])


def bin_image(img: np.ndarray, factor: int) -> np.ndarray:
    """Box-average (C, H, W) by `factor` (a remainder at the bottom/right is dropped)."""
    if factor == 1:
        return np.asarray(img, np.float64)
    c, h, w = img.shape
    h2, w2 = h // factor, w // factor
    return np.asarray(img[:, :h2 * factor, :w2 * factor], np.float64).reshape(
        c, h2, factor, w2, factor).mean(axis=(2, 4))


def warp_to(img: np.ndarray, h: np.ndarray, shape: tuple[int, int],
            interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """(C, h, w) image resampled onto a grid of `shape`: out(x) = img(H^-1 x); zero outside."""
    return np.stack([cv2.warpPerspective(np.ascontiguousarray(ch, np.float64), np.asarray(h, np.float64),
                                         (shape[1], shape[0]), flags=interpolation,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0) for ch in img])


def warp_exact(img: np.ndarray, h: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Like `warp_to` but with cubic-spline interpolation at exact (unquantised) positions.
    OpenCV's warps resolve positions to 1/32 pixel, which leaves the least-squares refinement
    with a piecewise-constant objective."""
    from scipy.ndimage import map_coordinates  # heavy: scipy

    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    src = apply_homography(np.linalg.inv(np.asarray(h, np.float64)), np.c_[xx.ravel(), yy.ravel()])
    coords = np.stack([src[:, 1], src[:, 0]])
    return np.stack([map_coordinates(np.asarray(ch, np.float64), coords, order=3, mode="grid-constant",
                                     cval=0.0).reshape(shape) for ch in img])


def _gray(img: np.ndarray) -> np.ndarray:
    return np.asarray(img, np.float64).mean(axis=0).astype(np.float32)


# --------------------------------------------------------------------------- estimation stages


def feature_init(gs: np.ndarray, rs: np.ndarray, model: str) -> tuple[np.ndarray, int] | None:
    """GS->RS transform from SIFT matches + RANSAC (None when too few inliers)."""
    def u8(img):
        g = _gray(img)
        lo, hi = np.percentile(g, [1, 99.5])
        return np.clip((g - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)

    sift = cv2.SIFT_create()
    kg, dg = sift.detectAndCompute(u8(gs), None)
    kr, dr = sift.detectAndCompute(u8(rs), None)
    if dg is None or dr is None or len(kg) < MIN_FEATURE_INLIERS or len(kr) < MIN_FEATURE_INLIERS:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dg, dr, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    if len(good) < MIN_FEATURE_INLIERS:
        return None
    src = np.float32([kg[m.queryIdx].pt for m in good])
    dst = np.float32([kr[m.trainIdx].pt for m in good])
    if model == "similarity":
        m, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=2.0)
        h = None if m is None else np.vstack([m, [0, 0, 1]])
    else:
        h, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 2.0)
    n = 0 if inliers is None else int(inliers.sum())
    if h is None or n < MIN_FEATURE_INLIERS:
        return None
    return np.asarray(h, np.float64), n


def ecc_refine(rs: np.ndarray, gs: np.ndarray, h0: np.ndarray, model: str,
               levels: int = 2) -> tuple[np.ndarray, float]:
    """ECC (coarse to fine) between the deconvolved RS image and the GS image warped by h0.
    Returns (GS->RS transform, final correlation coefficient)."""
    shape = rs.shape[-2:]
    motion = cv2.MOTION_HOMOGRAPHY if model == "homography" else cv2.MOTION_AFFINE
    template = _gray(rs)
    moving = _gray(warp_to(gs, h0, shape))
    valid = (warp_to(np.ones((1, *gs.shape[-2:])), h0, shape)[0] > 0.999).astype(np.uint8)
    w = np.eye(3, dtype=np.float32)
    cc = float("nan")
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    for level in reversed(range(levels)):
        f = 2 ** level
        if min(shape) // f < 16:
            continue
        size = (shape[1] // f, shape[0] // f)
        t = cv2.resize(template, size, interpolation=cv2.INTER_AREA)
        m = cv2.resize(moving, size, interpolation=cv2.INTER_AREA)
        mask = cv2.resize(valid, size, interpolation=cv2.INTER_NEAREST)
        s = bin_matrix(f).astype(np.float32)
        w_level = s @ w @ np.linalg.inv(s)
        try:
            cc, w_level = cv2.findTransformECC(t, m, w_level[:3] if motion == cv2.MOTION_HOMOGRAPHY
                                               else w_level[:2], motion, criteria, mask, 3)
        except cv2.error as exc:
            raise AlignmentError(f"ECC alignment did not converge ({str(exc).strip().splitlines()[-1]}); "
                                 "is the target textured and inside both fields of view?") from None
        full = np.eye(3, dtype=np.float32)
        full[:w_level.shape[0]] = w_level
        w = np.linalg.inv(s) @ full @ s
    # moving(W x) ~ template(x) and moving(y) = GS(h0^-1 y), so GS->RS = W^-1 h0.
    h = np.linalg.inv(w.astype(np.float64)) @ h0
    if model == "similarity":
        pts = grid_points(gs.shape[-2:], fraction=0.8)
        h = fit_similarity(pts, apply_homography(h, pts))
    return h / h[2, 2], cc


def _params(h: np.ndarray, model: str) -> np.ndarray:
    if model == "similarity":
        return np.array([h[0, 0], h[1, 0], h[0, 2], h[1, 2]])
    return (h / h[2, 2]).ravel()[:8]


def _matrix(p: np.ndarray, model: str) -> np.ndarray:
    if model == "similarity":
        a, b, tx, ty = p
        return np.array([[a, -b, tx], [b, a, ty], [0, 0, 1.0]])
    return np.append(p, 1.0).reshape(3, 3)


class ForwardFit:
    """Predicts the RS image of a static scene from the GS image: (e_RS / e_GS) PSF * warp(GS)."""

    def __init__(self, rs: np.ndarray, gs: np.ndarray, psf: np.ndarray, exposure_ratio: float):
        self.rs, self.gs = np.asarray(rs, np.float64), np.asarray(gs, np.float64)
        self.shape = self.rs.shape[-2:]
        self.ratio = float(exposure_ratio)
        self.op = PSFConvolution(torch.from_numpy(np.asarray(psf, np.float64)), self.shape,
                                 channels=self.rs.shape[0])

    def predict(self, h: np.ndarray) -> np.ndarray:
        """Unit-gain prediction (C, H, W) for transform h."""
        warped = torch.from_numpy(warp_exact(self.gs, h, self.shape))
        return self.ratio * self.op.A(warped).numpy()

    def gains(self, pred: np.ndarray) -> np.ndarray:
        """Per-channel least-squares Lambda with rs ~ Lambda * pred."""
        num = (pred * self.rs).sum(axis=(1, 2))
        den = (pred * pred).sum(axis=(1, 2))
        if np.any(den <= 0):
            raise AlignmentError("the warped GS image has no signal in some channel; "
                                 "does the target lie inside the GS field of view?")
        return num / den

    def residual(self, h: np.ndarray) -> np.ndarray:
        pred = self.predict(h)
        return (self.gains(pred)[:, None, None] * pred - self.rs).ravel()

    def misfit(self, h: np.ndarray) -> float:
        """RMS residual relative to the RS image's RMS."""
        r = self.residual(h)
        return float(np.sqrt((r * r).mean() / (self.rs * self.rs).mean()))


def refine_forward(fit: ForwardFit, h0: np.ndarray, model: str,
                   points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares transform parameters (module docstring, step 4). Returns the transform and
    its 1-sigma position uncertainty (pixels; the largest over `points`, GS coordinates), from
    the fit's covariance sigma^2 (J^T J)^-1 with sigma^2 from the residual."""
    from scipy.optimize import least_squares  # heavy: scipy

    p0 = _params(h0, model)
    scale = np.abs(p0).clip(1e-3) if model == "homography" else np.array([1e-2, 1e-2, 1.0, 1.0])
    res = least_squares(lambda p: fit.residual(_matrix(p, model)), p0, x_scale=scale,
                        diff_step=1e-4, method="trf", max_nfev=200)
    jac = np.asarray(res.jac, np.float64)
    dof = max(jac.shape[0] - jac.shape[1], 1)
    try:
        cov = np.linalg.inv(jac.T @ jac) * (2 * res.cost / dof)
    except np.linalg.LinAlgError:
        return _matrix(res.x, model), float("nan")
    # Position Jacobian d(point)/d(params) by central differences, then per-point variance.
    base = apply_homography(_matrix(res.x, model), points)
    dpos = np.empty((len(points), 2, len(res.x)))
    for k in range(len(res.x)):
        step = np.zeros_like(res.x)
        step[k] = 1e-6 * max(1.0, abs(res.x[k]))
        dpos[:, :, k] = (apply_homography(_matrix(res.x + step, model), points) - base) / step[k]
    var = np.einsum("nik,kl,nil->n", dpos, cov, dpos)
    return _matrix(res.x, model), float(np.sqrt(max(var.max(), 0.0)))


def tile_shifts(rs: np.ndarray, gs_warped: np.ndarray, valid: np.ndarray, tile: int) -> np.ndarray:
    """(N, 2) local shifts (x, y) between two images on textured tiles fully inside `valid`."""
    a, b = _gray(rs).astype(np.float64), _gray(gs_warped).astype(np.float64)
    h, w = a.shape
    window = cv2.createHanningWindow((tile, tile), cv2.CV_64F)
    shifts = []
    for y0 in range(0, h - tile + 1, tile // 2):
        for x0 in range(0, w - tile + 1, tile // 2):
            if not valid[y0:y0 + tile, x0:x0 + tile].all():
                continue
            ta, tb = a[y0:y0 + tile, x0:x0 + tile], b[y0:y0 + tile, x0:x0 + tile]
            if tb.std() < 0.05 * max(b.std(), 1e-12) or ta.std() <= 0:
                continue
            (dx, dy), response = cv2.phaseCorrelate(tb, ta, window)
            if response > 0.05 and abs(dx) < tile / 4 and abs(dy) < tile / 4:
                shifts.append((dx, dy))
    return np.asarray(shifts, np.float64).reshape(-1, 2)


# --------------------------------------------------------------------------- the whole thing


@dataclass
class Alignment:
    """Result on the working grids (gs_to_rs maps GS working pixels to RS working pixels)."""

    gs_to_rs: np.ndarray
    white_balance: np.ndarray
    ecc: float
    residual_px: float  # median local shift, deconvolved RS vs warped GS (includes deconvolution noise)
    residual_tiles: int
    uncertainty_px: float  # 1-sigma position uncertainty of the refined transform (nan without it)
    misfit: float
    init: str
    deconvolved: np.ndarray
    notes: list[str] = field(default_factory=list)


def align_images(rs: np.ndarray, gs: np.ndarray, psf: np.ndarray, exposure_ratio: float,
                 init: np.ndarray | None = None, model: str = "similarity", refine: bool = True,
                 deconv_iters: int = 100, tau_rel: float = 1e-3) -> Alignment:
    """Align a GS image (C, h, w) to an RS image (C, H, W) of the same static scene (operator
    units, on working grids) with the RS PSF (C or 1, Hp, Wp) on the RS grid. `exposure_ratio`
    is e_RS / e_GS. See the module docstring for the steps."""
    with few_threads(int(np.prod(np.shape(rs)[-2:]))):
        return _align_images(rs, gs, psf, exposure_ratio, init, model, refine, deconv_iters, tau_rel)


def _align_images(rs, gs, psf, exposure_ratio, init, model, refine, deconv_iters, tau_rel) -> Alignment:
    if model not in MODELS:
        raise AlignmentError(f"unknown transform model {model!r}; use one of {', '.join(MODELS)}")
    rs, gs = np.asarray(rs, np.float64), np.asarray(gs, np.float64)
    if rs.ndim != 3 or gs.ndim != 3 or rs.shape[0] != gs.shape[0]:
        raise AlignmentError(f"RS and GS images must be (C, H, W) with equal C, got {rs.shape} and {gs.shape}")
    for name, img in (("RS", rs), ("GS", gs)):
        if not np.all(np.isfinite(img)):
            raise AlignmentError(f"the {name} image contains NaN or Inf")
        if img.std() <= 0:
            raise AlignmentError(f"the {name} image is flat: point the cameras at a textured target")
    notes: list[str] = []
    deconv = deconvolve(rs, psf, tau_rel=tau_rel, iters=deconv_iters)
    x = deconv.image
    candidates: list[tuple[str, np.ndarray]] = []
    if init is not None:
        candidates.append(("given", np.asarray(init, np.float64)))
    found = feature_init(gs, x, model)
    if found is not None:
        candidates.append((f"features ({found[1]} RANSAC inliers)", found[0]))
    if not candidates:
        candidates.append(("identity", np.eye(3)))
    best = None
    for name, h0 in candidates:
        try:
            h, cc = ecc_refine(x, gs, h0, model)
        except AlignmentError as exc:
            notes.append(f"ECC from {name} start failed: {exc}")
            continue
        if best is None or cc > best[2]:
            best = (name, h, cc)
    if best is None:
        raise AlignmentError(notes[-1].split(": ", 1)[1])
    init_name, h, cc = best
    fit = ForwardFit(rs, gs, psf, exposure_ratio)
    if refine:
        h_ecc, misfit_ecc = h, fit.misfit(h)
        h, uncertainty = refine_forward(fit, h, model, grid_points(gs.shape[-2:]))
        if fit.misfit(h) > misfit_ecc:  # never accept a worse fit
            h, uncertainty = h_ecc, float("nan")
            notes.append("the forward-model refinement did not improve on ECC; kept the ECC transform")
    else:
        uncertainty = float("nan")
    h = h / h[2, 2]
    wb = fit.gains(fit.predict(h))
    if np.any(~np.isfinite(wb)) or np.any(wb <= 0):
        raise AlignmentError(f"white balance is not positive ({wb.tolist()}); check the target")
    shape = rs.shape[-2:]
    valid = warp_to(np.ones((1, *gs.shape[-2:])), h, shape)[0] > 0.999
    outside = float(x[:, ~valid].sum() / max(x.sum(), 1e-300))
    if outside > OUTSIDE_LIGHT_WARN:
        notes.append(f"{outside:.1%} of the deconvolved RS light lies outside the GS field of view; keep "
                     "the target inside both fields (the white balance and the refinement assume it)")
    tile = int(max(16, 2 ** round(math.log2(max(min(shape) // 4, 16)))))
    shifts = tile_shifts(x, warp_to(gs, h, shape), valid, tile)
    residual = float(np.median(np.hypot(shifts[:, 0], shifts[:, 1]))) if len(shifts) else float("nan")
    if not len(shifts):
        notes.append("no textured tile for the residual check")
    return Alignment(gs_to_rs=h, white_balance=wb, ecc=float(cc), residual_px=residual,
                     residual_tiles=len(shifts), uncertainty_px=uncertainty, misfit=fit.misfit(h), init=init_name,
                     deconvolved=x, notes=notes)


def working_factor(shape: tuple[int, int], max_side: int) -> int:
    """Smallest integer bin that brings the long side of `shape` to at most `max_side`."""
    return max(1, math.ceil(max(shape) / max_side))


@dataclass
class WorkingPair:
    """A static RS/GS pair binned to working grids, the PSF on the RS working grid, and the
    maps between raw and working pixel coordinates (x_work = B x_raw)."""

    rs: np.ndarray
    gs: np.ndarray
    psf: np.ndarray
    b_rs: np.ndarray
    b_gs: np.ndarray
    grid: dict

    def to_work(self, h_raw: np.ndarray) -> np.ndarray:
        return self.b_rs @ np.asarray(h_raw, np.float64) @ np.linalg.inv(self.b_gs)

    def to_raw(self, h_work: np.ndarray) -> np.ndarray:
        h = np.linalg.inv(self.b_rs) @ h_work @ self.b_gs
        return h / h[2, 2]

    def centred_init(self) -> np.ndarray:
        """Working-grid transform that centres the GS field on the RS field at a common scale."""
        (hr, wr), (hg, wg) = self.rs.shape[-2:], self.gs.shape[-2:]
        h = similarity_matrix((0, 0), 0.0, min(wr / wg, hr / hg), ((wg - 1) / 2, (hg - 1) / 2))
        h[:2, 2] += np.array([(wr - wg) / 2, (hr - hg) / 2])
        return h


def working_pair(rs: np.ndarray, gs: np.ndarray, psf: np.ndarray, rs_mosaic: int = 1,
                 gs_mosaic: int = 1, max_side: int = 256) -> WorkingPair:
    """`rs` (C, H, W) and `gs` (C, h, w) in operator units after any Bayer binning by
    `rs_mosaic` / `gs_mosaic`, `psf` (C or 1, Hs, Ws) on the raw RS sensor grid -> working
    grids: the RS image binned to a long side <= max_side, the GS image binned to about the
    same size, the PSF area-resampled to the RS working pixel."""
    f_rs = working_factor(rs.shape[-2:], max_side)
    rs_w = bin_image(np.asarray(rs, np.float64), f_rs)
    f_gs = max(1, round(max(gs.shape[-2:]) / max(rs_w.shape[-2:])))
    gs_w = bin_image(np.asarray(gs, np.float64), f_gs)
    psf = np.asarray(psf, np.float64)
    psf = psf[None] if psf.ndim == 2 else psf
    bin_rs = rs_mosaic * f_rs
    psf_shape = (max(1, round(psf.shape[-2] / bin_rs)), max(1, round(psf.shape[-1] / bin_rs)))
    psf_w = normalise(resample(psf, psf_shape)) if psf_shape != psf.shape[-2:] else normalise(psf)
    grid = {"rs_bin": bin_rs, "gs_bin": gs_mosaic * f_gs, "rs_work_shape": list(rs_w.shape[-2:]),
            "gs_work_shape": list(gs_w.shape[-2:])}
    return WorkingPair(rs_w, gs_w, psf_w, bin_matrix(bin_rs), bin_matrix(gs_mosaic * f_gs), grid)


def align_pair(pair: WorkingPair, exposure_ratio: float, init: np.ndarray | None = None,
               model: str = "similarity", refine: bool = True, deconv_iters: int = 100,
               tau_rel: float = 1e-3) -> Alignment:
    """`align_images` on a working pair; `init` and the result's gs_to_rs are raw GS pixel ->
    raw RS pixel transforms, residual_px is in raw RS pixels."""
    if init is not None:
        init_w = pair.to_work(init)
    elif pair.rs.shape[-2:] != pair.gs.shape[-2:]:
        init_w = pair.centred_init()
    else:
        init_w = None
    result = align_images(pair.rs, pair.gs, pair.psf, exposure_ratio, init=init_w, model=model,
                          refine=refine, deconv_iters=deconv_iters, tau_rel=tau_rel)
    result.gs_to_rs = pair.to_raw(result.gs_to_rs)
    result.residual_px *= pair.grid["rs_bin"]
    result.uncertainty_px *= pair.grid["rs_bin"]
    return result
