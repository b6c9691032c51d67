"""Before/after strip of the demo's sineball scene from estimates saved by bench/stfm_motion.py.

    .venv/bin/python -m bench.demo_strip --runs /tmp/stfm_runs/new --size 64 \
        --show stfm-fast=fast,stfm-prior=prior --out bench/demo_strip_sineball.png

Rows: the truth, then each `label=config` whose `sineball<size>_<config>.npy` is in `--runs`;
columns: the frames the demo shows (0, K/6, K/3, K/2, 2K/3, 5K/6), or `--frames`. Uses
the demo's strip function (rngcam.evaluate.strips), so the picture reads like the demo's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from rngcam.evaluate.scenes import scene_problem as simulated_problem
from rngcam.evaluate.strips import strip_png


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, required=True)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--show", required=True, help="comma-separated label=config")
    ap.add_argument("--frames", help="comma-separated frame indices")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    problem, _ = simulated_problem("sineball", args.size)
    truth = problem.truth.float().numpy()
    k = truth.shape[1]
    frames = ([int(f) for f in args.frames.split(",")] if args.frames
              else [0, k // 6, k // 3, k // 2, 2 * k // 3, 5 * k // 6])
    videos = {}
    for item in args.show.split(","):
        label, _, config = item.partition("=")
        videos[label] = np.load(args.runs / f"sineball{args.size}_{config or label}.npy").astype(np.float32)
    strip_png(args.out, truth, videos, frames)
    print(f"wrote {args.out} (frames {frames})")


if __name__ == "__main__":
    main()
