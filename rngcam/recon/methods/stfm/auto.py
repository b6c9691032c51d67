"""`preset="auto"`: the prior preset where one translating layer explains the key frames, else fast.

The prior preset (one canonical dynamic image moved by a smooth motion field) recovers an object
that moves, turns and comes back (sineball), and collapses where the scene is not one moving
layer (smoke that appears, a street clip: under the GS-only baselines; bench/stfm_motion.md).
The fast preset (a correction of GS-only interpolations) never falls far under those baselines
but smears a moving object. Neither the RS residual nor held-out RS rows separate the two: both
fit the RS image, held-out rows included, to about its noise (bench/stfm_motion.md).

What does separate them is in the key frames, before any fit: the prior preset's start is the
middle key frame's moving part (where it differs from the key frames' median) pasted over that
median at a shift (rngcam.recon.methods.stfm.motion_search). If some shift of it reproduces each other
key frame, the scene is one layer that translates; if not (smoke grows, cars and walkers move
differently, the camera pans), it is not. The test: for each other key frame g,

    misfit_g = min over shifts d of ||F(d) - key_g||^2 / ||median - key_g||^2

(F(d): the layer shifted by d over the median; the denominator is what moved in key frame g).
The prior preset is chosen when the largest of them is below the auto_preset stage's layer_misfit_max:
the layer must explain every key frame. A mean let one key frame the layer explains well hide one it
does not: a camera pan (half its key frames' misfits over the threshold, mean under it; the prior's
canonical image spans the frame, so what the pan brings in has no place in it) and an object that
enters between key frames (misfits 0.99 and 0.01) (bench/untuned.md, "the layer test's worst key frame"). It costs one
composite per candidate shift and key frame, no fit. Key frames larger than `layer_test_side` are
binned down to about it first: the threshold was set on 32-64 px key frames, and at full size the
test took much of a large grid's set-up (bench/convergence.md, "the layer test binned").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from rngcam.recon.methods.coarse_to_fine import bin_video
from rngcam.recon.methods.stfm.motion_search import candidate_shifts, key_frame_layer, shifted_frames
from rngcam.recon.methods.stfm.stage_configs import AutoPresetConfig

CHUNK_ELEMENTS = 8_000_000  # composited values held at once (32 MB of float32 per temporary)
MISFIT_DIGITS = 4  # the misfits as a run records them (metrics.json), and as the test compares them


@dataclass
class PresetChoice:
    """The preset `auto` resolved to, and why."""

    preset: str
    reason: str
    misfits: list[float] = field(default_factory=list)  # per key frame other than the middle one
    misfit_max: float = AutoPresetConfig.layer_misfit_max

    def as_dict(self) -> dict:
        return {"preset": self.preset, "reason": self.reason, "layer_misfits": self.misfits,
                "layer_misfit_max": self.misfit_max}


@torch.no_grad()
def layer_misfits(keys: Tensor, mask: Tensor | None = None,
                  test_side: int = AutoPresetConfig.layer_test_side) -> list[float]:
    """misfit_g (module docstring) of every key frame but the middle one; keys (C, G, H, W), binned
    first where larger than `test_side`."""
    keys, mask = _binned(keys.float(), mask, test_side)
    c, g, h, w = keys.shape
    middle = g // 2
    background, layer, obj = key_frame_layer(keys, middle)
    shifts, _, _ = candidate_shifts(h, w, keys.device)
    weight = torch.ones(h, w, device=keys.device) if mask is None else mask.to(keys.device, torch.float32)
    chunk = max(1, CHUNK_ELEMENTS // (c * h * w))
    out = []
    for i in range(g):
        if i == middle:
            continue
        target = keys[:, i]
        moved = float(((background - target) * weight).square().sum())
        best = float("inf")
        for j in range(0, len(shifts), chunk):
            frames = shifted_frames(background, layer, obj, shifts[j:j + chunk])
            best = min(best, float(((frames - target[None]) * weight).square().sum((1, 2, 3)).min()))
        out.append(best / moved if moved > 0 else float("inf"))
    return out


def _binned(keys: Tensor, mask: Tensor | None, test_side: int) -> tuple[Tensor, Tensor | None]:
    """Key frames (C, G, H, W) and mask (H, W) binned by area as `coarsen` bins a problem, by
    f = the longer side // `test_side` (as they are where f < 2); the mask becomes a weight."""
    c, g, h, w = keys.shape
    f = max(h, w) // test_side
    if f < 2:
        return keys, mask
    shape = (c, g, max(1, round(h / f)), max(1, round(w / f)))
    if mask is not None:
        mask = bin_video(mask.to(keys)[None, None], (1, 1, *shape[2:]), 1)[0, 0]
    return bin_video(keys, shape, 1), mask


def choose_preset(problem, config: AutoPresetConfig | None = None) -> PresetChoice:
    """The preset for `problem` (see the module docstring); it looks at the GS key frames only
    (held-out GS pixels filled from fitted ones, as every initialisation does). `config`: the
    auto_preset stage's (its defaults where None)."""
    config = config or AutoPresetConfig()
    misfit_max = config.layer_misfit_max
    if problem.b_gs is None or problem.b_gs.shape[1] < 2:
        return PresetChoice("fast", "fewer than two GS key frames: no layer test")
    keys = problem.gs_images(gains=True)
    if not torch.isfinite(keys).all():
        return PresetChoice("fast", "non-finite key frames: no layer test")
    misfits = [round(m, MISFIT_DIGITS) for m in layer_misfits(keys, problem.mask, config.layer_test_side)]
    worst = max(misfits)
    if worst < misfit_max:
        return PresetChoice("prior", f"one translating layer explains every key frame (largest misfit "
                                     f"{worst:.3f} < {misfit_max}): the paper's prior", misfits, misfit_max)
    return PresetChoice("fast", f"one translating layer does not explain key frame {misfits.index(worst) + 1} "
                                f"of {len(misfits)} others (misfit {worst:.3f} >= {misfit_max}): the prior preset "
                                "would collapse there", misfits, misfit_max)
