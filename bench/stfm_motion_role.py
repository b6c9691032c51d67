"""What the motion field does in one fast-preset fit on smoke 64 (bench/stfm_compare.md, session 10).

    PYTHONPATH=. nice -n 10 .venv/bin/python -m bench.stfm_motion_role --bases video,keys

Per base, with and without the motion TV, each fit to its own stop (so the load does not matter):
PSNR, the size of the learned motion u in pixels (for "keys" bases without the RIFE flows that u
corrects), and the PSNR of the same fit's video with u set to zero: what the motion field carries.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from rngcam.evaluate.scenes import scene_problem as simulated_problem
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.metrics import motion_metrics, video_metrics
from rngcam.recon.runner import method_view


def score(video: torch.Tensor, problem) -> str:
    inter, truth = problem.intermediate_frames(), problem.truth.double()
    db = video_metrics(video.float(), truth.float(), inter)["psnr_intermediate_db"]
    moving = motion_metrics(video.double(), truth, inter, one_object=False)["psnr_dynamic_db"]
    return f"{db:.2f} dB interm., moving {moving:.2f}"


@torch.no_grad()
def learned_motion_px(fit) -> np.ndarray:
    """|u| (K, H, W) in pixels: the fitted motion without the key-frame flows it corrects."""
    u = fit.components()["motion"]  # (2, K, H, W), key flows included
    if fit._key_warps:
        u = u - (fit.base.key_flow[..., :2] * fit.grid.px_per_unit).permute(3, 0, 1, 2).cpu().numpy()
    return np.sqrt((u ** 2).sum(0))


@torch.no_grad()
def without_motion(fit) -> torch.Tensor:
    """The fit's video with its motion field replaced by zero."""
    width = 4 if fit._key_warps else 2
    fit.model.motion = lambda idx: torch.zeros(len(idx), fit.H, fit.W, width, device=fit.device)
    fit._cache = None
    return fit.estimate().detach()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bases", default="video,keys")
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args()
    torch.set_num_threads(1)
    problem, _ = simulated_problem("smoke", args.size)
    truth = problem.truth.double()
    moving = ((truth - truth.median(1, keepdim=True).values).abs().amax(0) > 0.02).numpy()  # (K, H, W)
    for base in args.bases.split(","):
        for no_reg in (False, True):
            fit = make_stfm(method_view(problem), STFMSettings(dynamic_base=base, components="all", no_motion_reg=no_reg))
            result = run(fit, LoopSettings(time_budget_s=1e4, max_iters=3000, progress=False, log_every_s=1e4))
            video = fit.estimate().detach()
            mag = learned_motion_px(fit)
            print(f"{base} no_motion_reg={no_reg}: {result.iterations} steps; {score(video, problem)}; |u| px: "
                  f"mean {mag.mean():.3f}, moving region {mag[moving].mean():.3f}, p99 {np.percentile(mag, 99):.2f}; "
                  f"u set to 0: {score(without_motion(fit), problem)}", flush=True)


if __name__ == "__main__":
    main()
