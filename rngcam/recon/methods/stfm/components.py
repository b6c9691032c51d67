"""Which parts of the STFM a problem needs (auto leave-out), and why the others were left out.

Rules (components="auto"), applied after the user's ablation flags:
- no GS frames -> RS-only fit; no RS measurement -> GS-only fit;
- a dark or empty background (the median of the GS frames, the background estimate, is below
  `dark_fraction` of the brightest GS pixels) -> no static field;
- the GS frames agree within their noise and the RS image predicted from their mean (as a
  static video, through the RS operator) matches the RS measurement within its noise -> a
  static scene: no motion field, no dynamic field (see `static_scene` for the tests).

Noise levels are estimated from the data (robust medians: of frame differences, and of the
finest diagonal Haar detail, Donoho & Johnstone 1994); no sensor model is needed. The thresholds are
the fit stage's (stage_configs.ComponentsConfig: `--set fit.dark_fraction=...`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm.stage_configs import ComponentsConfig
from rngcam.recon.noise import image_noise_std

PEAK_QUANTILE = 0.999  # the GS frames' peak: a high quantile, not the maximum (a hot pixel is no peak)
PEAK_SAMPLES = 1_000_000  # ... of at most this many values (torch.quantile's input limit is 16 M)
MAD_TO_SIGMA = 0.6745  # a normal distribution's median absolute deviation, in sigmas


@dataclass(frozen=True)
class Components:
    """What the fit uses; `left_out` lists (component, reason) for everything switched off."""

    static: bool = True
    motion: bool = True  # the motion field and the dynamic field (off: a static video)
    motion_reg: bool = True
    rs: bool = True
    gs: bool = True
    left_out: tuple[tuple[str, str], ...] = ()


def _rms(x: Tensor) -> float:
    return float(x.double().square().mean().sqrt())


def dark_background(problem, config: ComponentsConfig | None = None) -> tuple[bool, str]:
    """Is the background (median of the GS frames) dark? Returns (dark, explanation)."""
    config = config or ComponentsConfig()
    v = problem.gs_images(gains=True)
    background = v.median(dim=1).values
    if problem.mask is not None:
        m = problem.mask.to(torch.bool)
        background, v = background[:, m], v[:, :, m]
    peak = float(torch.quantile(v.double().flatten()[:PEAK_SAMPLES], PEAK_QUANTILE))
    level = float(background.double().mean())
    if peak <= 0:
        return True, "the GS frames are black"
    dark = level < config.dark_fraction * peak
    return dark, f"background level {level:.3g} is {100 * level / peak:.2g}% of the GS peak {peak:.3g}"


def gs_image_noise_std(v: Tensor) -> float:
    """Noise sigma of GS frames (C, G, H, W): the smaller of two robust estimates, the MAD of
    frame differences (texture cancels; fooled only when most pixels move) and the Haar
    estimate of each frame (fooled by dense texture)."""
    g = v.shape[1]
    pairs = [float((v[:, i] - v[:, j]).double().abs().median()) / MAD_TO_SIGMA / 2 ** 0.5
             for i in range(g) for j in range(i + 1, g)]
    return min(pairs + [image_noise_std(v[:, i]) for i in range(g)])


def static_scene(problem, rs_on: bool, config: ComponentsConfig | None = None) -> tuple[bool, str]:
    """Do the GS frames agree, and (with RS) does their mean predict the RS image, within noise?

    GS: no more than `static_outlier_fraction` of the pixels of any frame may differ from the
    mean frame by more than `static_noise_factor` noise sigmas (+ `static_relative_tol` of the
    value). RS: the residual of the static prediction must look like white noise: its RMS
    within `static_noise_factor` / 2 of its own Haar noise estimate (+ `static_relative_tol` of
    the RS image's RMS); motion leaves a smooth, structured residual behind the diffuser.
    """
    config = config or ComponentsConfig()
    v = problem.gs_images(gains=True)
    g = v.shape[1]
    if g < 2:
        return False, "a single GS frame cannot show motion"
    mean = v.mean(dim=1)
    sigma = gs_image_noise_std(v) * ((g - 1) / g) ** 0.5
    limit = config.static_noise_factor * sigma + config.static_relative_tol * mean.abs()
    moving = max(float(((v[:, i] - mean).abs() > limit).double().mean()) for i in range(g))
    if moving > config.static_outlier_fraction:
        return False, f"{100 * moving:.2g}% of GS pixels change beyond noise (sigma {sigma:.3g})"
    why = f"GS frames agree within noise (sigma {sigma:.3g}, {100 * moving:.2g}% outliers)"
    if not rs_on:
        return True, why
    op = problem.rs_op()
    mask = 1.0 if problem.mask is None else problem.mask.to(mean.dtype)
    static_video = (mean * mask)[:, None].expand(*problem.shape).to(problem.b_rs.dtype)
    residual = op.A(static_video.contiguous()) - problem.b_rs
    if getattr(problem, "rs_train_rows", None) is not None:  # held-out rows are not looked at
        residual = residual[:, problem.rs_train_rows.to(residual.device)]
    rms, white = _rms(residual), image_noise_std(residual)
    allowed = 0.5 * config.static_noise_factor * white + config.static_relative_tol * _rms(problem.b_rs)
    if rms > allowed:
        return False, (f"the RS image is not explained by a static scene (residual RMS {rms:.3g} "
                       f"> {allowed:.3g}, noise {white:.3g})")
    return True, f"{why}, and their mean predicts the RS image (residual RMS {rms:.3g} <= {allowed:.3g})"


def choose_components(problem, auto: bool = True, no_static: bool = False,
                      no_motion_reg: bool = False, no_rs: bool = False, no_gs: bool = False,
                      tau: float = 1.0, config: ComponentsConfig | None = None) -> Components:
    """Decide the components from the flags and (if `auto`) from the problem itself, by `config`'s
    thresholds (the fit stage's: its defaults where None)."""
    left: list[tuple[str, str]] = []
    has_rs = problem.b_rs is not None
    has_gs = problem.b_gs is not None and problem.b_gs.shape[1] > 0
    rs = has_rs and not no_rs
    gs = has_gs and not no_gs
    if no_rs:  # (an ablated problem has no RS image left: rngcam.recon.ablation)
        left.append(("rs", "switched off (no_rs): GS-only fit"))
    elif not has_rs:
        left.append(("rs", "no RS measurement: GS-only fit"))
    if no_gs:
        left.append(("gs", "switched off (no_gs): RS-only fit"))
    elif not has_gs:
        left.append(("gs", "no GS frames: RS-only fit"))
    if not (rs or gs):
        raise ConfigError("nothing to fit: the problem has neither a usable RS image nor GS frames")

    static, motion = True, True
    if no_static:
        static = False
        left.append(("static", "switched off (no_static)"))
    elif auto and gs:
        dark, why = dark_background(problem, config)
        if dark:
            static = False
            left.append(("static", f"dark background: {why}"))
    if auto and gs and not no_static:  # (a static video with no static field is a contradiction)
        still, why = static_scene(problem, rs_on=rs, config=config)
        if still:
            motion = False
            left.append(("motion", f"static scene: {why}"))
            left.append(("dynamic", "static scene: the static field is the whole video"))
            if not static:  # a static video needs the static field after all
                static = True
                left = [item for item in left if item[0] != "static"]
    motion_reg = motion
    if motion and no_motion_reg:
        motion_reg = False
        left.append(("motion_reg", "switched off (no_motion_reg)"))
    elif motion and tau == 0:
        motion_reg = False
        left.append(("motion_reg", "tau = 0"))
    return Components(static=static, motion=motion, motion_reg=motion_reg, rs=rs, gs=gs,
                      left_out=tuple(left))
