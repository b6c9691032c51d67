"""How much of a video's error can the two cameras see at all? (issue 19: why smoke stops short of 32 dB)

Usage:
    python -m bench.null_space --scene smoke --size 64 [--video stfm.npy ...] [-o bench/out/null_space.md]

For a video s (a GS-only baseline, or a reconstruction saved as a (C, K, H, W) .npy), its error
e = truth - s splits into the part the stacked operator [RS; GS] sees (its projection onto the
operator's row space, P e) and the part it cannot see (the null space). s + P e is the best video
that any method which only adds what the measurements can check to s could reach, with noise-free
data fitted exactly: the *data-consistent bound*. P e is the minimum-norm least-squares solution of
A d = A e, found by CGLS from d = 0 (its iterates stay in the row space); its PSNR is printed after
10, 30, 100 and 300 steps (a few hundred suffice at 64 px). A method beats the bound only through its
prior: by guessing the unseen part. The table's last column is the share of the error's energy the
cameras see.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch

from rngcam.evaluate.scenes import gs_only_video
from rngcam.evaluate.scenes import scene_problem as simulated_problem
from rngcam.recon import registry
from rngcam.recon.metrics import psnr, psnr_dynamic

GS_ONLY = registry.labels(registry.GS_ONLY)

MARKS = (10, 30, 100, 300)


def seen_part(problem, error: torch.Tensor, marks=MARKS) -> dict[int, torch.Tensor]:
    """The error's projection onto the row space of [RS; GS] after each of `marks` CGLS steps."""
    rs, gs = problem.rs_op(), problem.gs_op()

    def forward(x):
        return rs.A(x), gs.A(x)

    def adjoint(y):
        return rs.A_adjoint(y[0]) + gs.A_adjoint(y[1])

    d = torch.zeros_like(error)
    r = forward(error)
    s = adjoint(r)
    q, gamma = s.clone(), float((s * s).sum())
    out = {}
    for k in range(1, max(marks) + 1):
        if gamma == 0:
            out.update({m: d.clone() for m in marks if m >= k})
            break
        aq = forward(q)
        alpha = gamma / sum(float((a * a).sum()) for a in aq)
        d.add_(q, alpha=alpha)
        r = tuple(ri - alpha * ai for ri, ai in zip(r, aq))
        s = adjoint(r)
        gamma_new = float((s * s).sum())
        q = s + (gamma_new / gamma) * q
        gamma = gamma_new
        if k in marks:
            out[k] = d.clone()
    return out


def bound_row(problem, name: str, video: torch.Tensor) -> dict:
    """PSNR (intermediate frames, and their moving region) of `video` and of its data-consistent bound."""
    truth, inter = problem.truth.double(), problem.intermediate_frames()
    error = truth - video

    def scores(v):
        return psnr(v[:, inter], truth[:, inter]), psnr_dynamic(v, truth, inter)

    seen = seen_part(problem, error)
    last = seen[max(MARKS)]
    return {"name": name, "start": scores(video), "bound": {k: scores(video + d) for k, d in seen.items()},
            "seen_share": float((last * last).sum() / (error * error).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="smoke", help="a simulated scene (sineball, smoke; clips need RNGCAM_DATA)")
    ap.add_argument("--size", type=int, default=64, help="grid side, px")
    ap.add_argument("--video", action="append", default=[], type=Path,
                    help="a reconstruction to bound too: a (C, K, H, W) .npy on the scene's grid (repeatable)")
    ap.add_argument("-o", "--out", type=Path, default=None, help="also write the table here (markdown)")
    a = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    problem, source = simulated_problem(a.scene, a.size)
    problem = problem.to(torch.float64)
    videos = [(n, torch.from_numpy(np.asarray(gs_only_video(n, problem), np.float64))) for n in (*GS_ONLY, "gs_mean")]
    videos += [(path.stem, torch.from_numpy(np.load(path).astype(np.float64))) for path in a.video]
    lines = [f"## Data-consistent bound, {a.scene} {a.size}x{a.size} ({source})", "",
             "PSNR on intermediate frames / their moving region, dB; the bound after n CGLS steps.", "",
             "| video | as is | " + " | ".join(f"bound @{k}" for k in MARKS) + " | error seen |",
             "|---" * (len(MARKS) + 3) + "|"]
    for name, video in videos:
        if video.shape != problem.truth.shape:
            raise SystemExit(f"{name}: shape {tuple(video.shape)}, the scene's video is {tuple(problem.truth.shape)}")
        r = bound_row(problem, name, video)
        cells = [f"{i:.2f} / {d:.2f}" for i, d in [r["start"], *r["bound"].values()]]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {100 * r['seen_share']:.1f} % |")
        print(lines[-1], flush=True)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
