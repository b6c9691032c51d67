"""The RS residual of a video over line-time factors: does a fit's video say where the line time is?

    python -m bench.line_time_search BUNDLE RECON_DIR [--lo 1.0 --hi 1.03 --step 0.002]

For the reconstruction's video (RECON_DIR/recon.h5) and, where the bundle has one, the truth: the relative
RS residual of all rows with the recorded line time times each factor (per-channel gains in closed form).
Prints one line per video: factor -> residual, and the factor where it is lowest (bench/realistic.md,
"A line time learned far off").
"""

from __future__ import annotations

import argparse

import h5py
import numpy as np
import torch

from rngcam.formats.bundle import read_bundle
from rngcam.physics.operators import RollingShutter
from rngcam.recon.metrics import relative_residual
from rngcam.recon.problem import build_problem


def residuals(problem, video: torch.Tensor, factors: np.ndarray) -> list[float]:
    """The relative RS residual of `video` (C, K, H, W) at each line-time factor, gains fitted per channel."""
    b = problem.b_rs.double()
    out = []
    for f in factors:
        op = RollingShutter(problem.psf.double(), problem.rs_weights_at(float(f)).double(), video.shape[-1],
                            video.shape[0])
        pred = op.A(video)
        gains = (pred * b).sum((1, 2), keepdim=True) / (pred * pred).sum((1, 2), keepdim=True)
        out.append(relative_residual(gains * pred, b))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bundle", help="the capture (an rngcam bundle)")
    p.add_argument("recon", help="a reconstruction's folder (its recon.h5)")
    p.add_argument("--lo", type=float, default=1.0, help="the lowest factor [1.0]")
    p.add_argument("--hi", type=float, default=1.03, help="the highest factor [1.03]")
    p.add_argument("--step", type=float, default=0.002, help="the factors' spacing [0.002]")
    a = p.parse_args(argv)
    problem = build_problem(read_bundle(a.bundle))
    factors = np.arange(a.lo, a.hi + a.step / 2, a.step)
    with h5py.File(f"{a.recon}/recon.h5", "r") as f:
        videos = {"fit": torch.from_numpy(f["video"][...]).double()}
    if problem.truth is not None:
        videos["truth"] = problem.truth.double()
    for name, video in videos.items():
        res = residuals(problem, video, factors)
        pairs = ", ".join(f"{f:.3f}: {r:.5f}" for f, r in zip(factors, res, strict=True))
        print(f"{name}: lowest at {factors[int(np.argmin(res))]:.3f} ({pairs})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
