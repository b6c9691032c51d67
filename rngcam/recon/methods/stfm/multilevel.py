"""STFM coarse to fine: the normal STFM build on a coarse grid, then finer grids that start from it.

Levels come from rngcam.recon.methods.coarse_to_fine (`coarsen`: the problem binned in space and time,
e.g. 1/4, 1/2 and the full grid at 228x342). The coarsest level is the ordinary STFM of the
settings (`make_stfm`: RIFE or flow bases, the fast preset's ensemble, the prior preset's motion
search), so the set-up work that does not scale with the grid (RIFE, optical flow, the motion
search, the GS initialisation fits) runs on 1/16 of the pixels and 1/4 of the frames. A coarse
level ends at its own stop test (noise level or stall), after `max_level_steps`, or, under a time budget,
once its steps have used their share of what the budget had left when it started (`fit.level_share` for a
base-video model, CoarseToFine's for the others; the numbers are the fit stage's: stage_configs.MultilevelConfig).

Each finer level starts from the level below, in the preset's own model:
- a model with a time-dependent dynamic field on a base video (fast; `dynamic_time=True`):
  one fit whose base video is the coarser level's estimate, upsampled (like the ensemble's
  refinement fit: a quarter of the learning rate, its static/alpha composition from the GS frames);
- a model without a base (prior, paper; one canonical dynamic image moved by the motion field):
  the same fields, their feature planes resampled to the finer level's plane sizes and the
  decoders copied, so the canonical image and the motion carry over (coordinates are in [-1, 1]
  on every level) and the level fits only what the coarser grid could not resolve.

A finer level's RS operator norm (the data term's scale) comes from a power iteration started at
the coarser level's last iterate, upsampled (STFM's `rs_norm_start`): it settles in a few iterations where a
cold start at the full grid took its six allowed ones and most of the level's set-up.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from rngcam.memory import release_free_memory
from rngcam.recon.methods.coarse_to_fine import (
    FINE_GS_MAX_PIXELS,
    CoarseToFine,
    bin_video,
    default_factors,
    power_norm,
    upsample,
)
from rngcam.recon.methods.coarse_to_fine import LEVEL_SHARE as DEFAULT_LEVEL_SHARE
from rngcam.recon.methods.selfcal import pose_matrix, warp
from rngcam.recon.methods.stfm.bases import _base_video, _network_device
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.presets import preset_table
from rngcam.recon.methods.stfm.settings import STFMSettings, _setting_or_preset
from rngcam.recon.methods.stfm.stage_configs import fit_config

NATIVE_CHUNK_FRAMES = 8  # frames warped at once into the GS camera's coordinates (the base is the largest buffer)


def stfm_levels(problem, settings: STFMSettings) -> tuple[int, ...]:
    """Spatial factors of the levels (coarse to fine); (1,) means a single level."""
    if not settings.coarse_to_fine or problem.gs_train_mask is not None:
        return (1,)
    factors = default_factors(problem.shape)
    small = min(problem.shape[-2:]) < 2 * fit_config(settings).base_min_side
    if factors != (1,) or small or settings.preset == "auto":
        return factors  # ("auto" is resolved before the levels are chosen: make_stfm)
    return (2, 1) if _setting_or_preset(settings, "dynamic_time") else factors


def stfm_time_factors(problem, factors: tuple[int, ...], with_base: bool = True) -> tuple[int, ...]:
    """The frames a coarse frame bins, per level: none on a base-video model's (fast) half-grid-first
    path (below 96 px), whose coarse level learns the GS-to-RS shift the full level keeps (binned in
    pairs, frames taught it a shift the truth does not have; bench/convergence.md, "the half grid first
    again"); elsewhere the spatial factors."""
    return (1,) * len(factors) if _half_grid_first(problem, factors, with_base) else factors


def _half_grid_first(problem, factors: tuple[int, ...], with_base: bool) -> bool:
    """Whether these levels are a base-video model's half grid first below 96 px (stfm_levels)."""
    return with_base and len(factors) > 1 and default_factors(problem.shape) == (1,)


def make_multilevel(problem, settings: STFMSettings, device, factors: tuple[int, ...], single,
                    clock=None, stage=None,
                    max_level_steps: int | None = None, carry: str = "auto") -> CoarseToFine:
    """STFM coarse to fine over `factors` (see the module docstring). `single(problem, settings)`
    builds the ordinary STFM of the coarsest level; `stage(message)` reports each level's set-up.
    `carry`: "auto" (the preset's way, above), or "fields" for a base-video model too (its base
    upsampled, its fields resampled: bench/large_grids.py `carry` compares the two). `max_level_steps`:
    the fit stage's `max_level_steps` where None."""
    config = fit_config(settings)
    # a level is no whole run; one fit a level (each level takes the fields of the fit before it)
    single_settings = replace(settings, coarse_to_fine=False, track_refit=False, fits=1)
    c, k, h, w = problem.shape
    with_base = preset_table(settings.preset, h, w, k)["dynamic_time"] if settings.dynamic_time is None \
        else settings.dynamic_time
    previous: list = []
    norm_vector: list[Tensor] = []  # the last level's power-iteration vector for ||A_R||

    def make(level, x0: Tensor | None):
        if x0 is None:  # the coarsest level: the ordinary build
            method = single(level, single_settings)
            if level.b_rs is not None:  # and a cold power-iteration vector (cheap here) for the next
                gen = torch.Generator().manual_seed(0)
                start = torch.randn(level.shape, generator=gen).to(level.b_rs)
                norm_vector[:] = [power_norm(level.rs_op(), start)[1]]
            previous[:] = [method]
            return method
        start = None
        pose, ratio = previous[-1].pose(), level.shape[-1] / _fit_of(previous[-1]).W
        if norm_vector:  # the power iteration takes it over (and scales it in place)
            coarse = norm_vector.pop().float()
            start = upsample(coarse, level.shape, level.shape[1] / coarse.shape[1])
            del coarse
        if with_base and carry == "fields":
            coarse = _fit_of(previous[-1])
            base = upsample(coarse.base.video.float(), level.shape, level.shape[1] / coarse.K)
            method = STFM(level, replace(single_settings, dynamic_base="video", dynamic_time=True,
                                         lr=_lr(single_settings, level)), device, base_video=base,
                          base_gains=coarse.base.gains, fields_from=coarse, rs_norm_start=start)
        elif with_base:
            coarse_shape, state = _fit_of(previous[-1]).problem.shape, _fit_of(previous[-1]).state
            previous.clear()  # the coarser fit is not needed any more: free it before building
            release_free_memory()
            if pose is not None:  # the estimate is in RS coordinates; the fields' base in the GS camera's
                x0 = _to_native(x0, pose * ratio, max(level.shape[-2:]) / 2)
            # a small grid: the GS-only video's detail on the start, which the fit then only refines
            detail = level.b_gs is not None and level.shape[-2] * level.shape[-1] <= FINE_GS_MAX_PIXELS
            if detail:
                x0 = _with_detail(level, x0, coarse_shape)
            method = _on_base(level, single_settings, device, x0, start, refinement=detail, state=state)
            if pose is not None and method.learned_pose.learned:  # (fields_from carries it in the other two ways)
                method.start_pose(pose * ratio)
        else:
            method = _from_fields(level, single_settings, device, _fit_of(previous[-1]), start)
        if level.shape != problem.shape and method.rs_norm_vector is not None:
            norm_vector[:] = [method.rs_norm_vector]  # for the next level (the full grid keeps none)
        method.rs_norm_vector = None
        previous[:] = [method]
        return method

    if not with_base:
        share = DEFAULT_LEVEL_SHARE
    else:
        half_grid = _half_grid_first(problem, factors, with_base)
        share = config.half_grid_level_share if half_grid else config.level_share
    return CoarseToFine(problem, make, factors, clock=clock, stage=stage, level_stop="method",
                        max_level_steps=config.max_level_steps if max_level_steps is None else max_level_steps,
                        time_factors=stfm_time_factors(problem, factors, with_base),
                        level_share=share)


def _fit_of(method) -> STFM:
    """The single fit whose fields a finer level takes (an ensemble's refinement or first member). A
    level may come wrapped by a refit stage, which hands on what its current fit has: so asked by
    attribute, not by type."""
    refined = getattr(method, "refined", None)
    if refined is not None:
        return refined
    members = getattr(method, "members", None)
    return members[0] if members else method


@torch.no_grad()
def _to_native(video: Tensor, pose: Tensor, radius: float) -> Tensor:
    """A video (C, K, H, W) in RS coordinates in the GS camera's (sampled at S p), in place, frame
    chunk by frame chunk (the full grid's base is the run's largest buffer)."""
    m = pose_matrix(pose.double().cpu(), radius).numpy()
    n = NATIVE_CHUNK_FRAMES
    for i in range(0, video.shape[1], n):
        video[:, i:i + n] = warp(video[:, i:i + n].float(), m).to(video.dtype)
    return video


@torch.no_grad()
def _with_detail(problem, x0: Tensor, coarse_shape: tuple[int, int, int, int]) -> Tensor:
    """x0 (the coarser estimate, upsampled) plus the detail of the GS-only video (RIFE's, else
    optical-flow interpolation's, on the RS scale) that the coarser grid could not hold: the video less
    its binning to `coarse_shape`, upsampled. The video is made of the frames the coarser level's bases
    were (without gains: RIFE's flows are those it already computed) and then put on the RS scale."""
    video = _base_video(problem.gs_images(), problem.gs_times_s, problem.frame_times_s, "video",
                        device=_network_device(x0.device))[0].to(x0.device, torch.float32)
    if problem.white_balance is not None:
        video.mul_(problem.white_balance.to(video)[:, None, None, None])
    frames = round(problem.shape[1] / coarse_shape[1])  # fine frames a coarse frame bins
    low = upsample(bin_video(video, coarse_shape, frames), problem.shape, frames)
    return video.sub_(low).add_(x0).clamp_min_(0)


def _lr(settings: STFMSettings, problem) -> float:
    c, k, h, w = problem.shape
    base = settings.lr if settings.lr is not None else preset_table(settings.preset, h, w, k)["lr"]
    return fit_config(settings).refine_lr_ratio * base


def _on_base(problem, settings: STFMSettings, device, x0: Tensor, norm_start: Tensor | None = None,
             refinement: bool = False, state=None) -> STFM:
    """One fit on the base video x0 (C, K, H, W), the coarser level's estimate upsampled (kept as
    it is, half precision included: no copy). The base is x0 divided by the gains the fit starts
    with (on the fly), so its first video is x0 itself. `refinement`: with the ensemble refinement's
    stall window (`fit.refine_stall_passes`, unless stall_passes is set), where x0 carries the GS-only
    detail (the default window stopped the paper grid's middle level early; bench/convergence.md,
    "the fast preset on the half grid first"). `state`: the run state of the level below
    (rngcam.recon.methods.stfm.run_state)."""
    wb = problem.white_balance
    gains = None if wb is None or bool(torch.all(wb == 1)) else wb.float()
    fine = replace(settings, dynamic_base="video", dynamic_time=True, lr=_lr(settings, problem))
    if refinement:
        fine = replace(fine, stall_passes=settings.stall_passes or fit_config(settings).refine_stall_passes)
    return STFM(problem, fine, device, base_video=x0, base_gains=gains, rs_norm_start=norm_start, state=state)


def _from_fields(problem, settings: STFMSettings, device, coarse: STFM, norm_start: Tensor | None = None) -> STFM:
    """The coarse fit's model on this level: its fields resampled, its gains, a quarter of the lr."""
    fine = replace(settings, lr=_lr(settings, problem))
    return STFM(problem, fine, device, fields_from=coarse, rs_norm_start=norm_start)
