"""Side-by-side benchmark of pnp and RIFE 4.x against tv3d and the GS-only baselines, by hand:

    flock /tmp/rngcam-bench.lock .venv/bin/python -m bench.pnp_compare --budget 300 --out bench/pnp_compare.md

In one process, one torch thread, on the CPU, each scene simulated by `rngcam.sim.simulate` at 64 px
(the three real clips at span 8):
1. on smoke: tv3d (defaults, and each extra `--tv3d-betas`), pnp (defaults: x-t/y-t slices), pnp on
   the frames only (`slices=xy`), pnp with the 2-D TV stand-in for FFDNet, and the GS-only baselines;
2. on the real clips (car, walk, vtest): pnp and the GS-only baselines (blend, interp, RIFE 4.x, RIFE HDv3);
3. RIFE 4.x against HDv3: seconds per interpolated frame at 64 and 256 px (two key frames of the car
   clip, 32 frames between them, the second of two runs).
Iterative methods get `--budget` seconds each (pnp stops itself earlier by its discrepancy/stall test).
PSNR is over all frames / over the intermediate frames (away from the GS key frames).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from rngcam.api import reconstruct
from rngcam.evaluate.scenes import scene_problem
from rngcam.paths import SHORT_CLIP, package_data
from rngcam.recon.methods.rife import rife
from rngcam.recon.metrics import video_metrics
from rngcam.recon.nets import ffdnet

GS_ROWS = ("blend", "interp", "rife 4.x", "rife hdv3", "rife mean (4.x + HDv3)")


def problem(scene: str, size: int, tmp: Path):
    """The scene (rngcam.evaluate.scenes) as a float32 problem with truth."""
    return scene_problem(scene, size)[0].to(torch.float32)


def scores(p, video) -> dict:
    m = video_metrics(torch.as_tensor(np.asarray(video)).double(), p.truth.double(), p.intermediate_frames(), p.mask)
    return {"psnr": m["psnr_db"], "inter": m["psnr_intermediate_db"]}


def gs_only(p) -> dict[str, dict]:
    out = {}
    videos = {}
    for name, label, overrides in (("blend", "blend", {}), ("interp", "interp", {}), ("rife 4.x", "rife", {"model": "4"}),
                                   ("rife hdv3", "rife", {"model": "hdv3"})):
        t0 = time.perf_counter()
        videos[name] = reconstruct(p, label, progress=False, **overrides).video
        out[name] = {**scores(p, videos[name]), "seconds": time.perf_counter() - t0, "note": ""}
    # pnp's other candidate start: a GS-only video too, so it competes as a baseline
    out["rife mean (4.x + HDv3)"] = {**scores(p, 0.5 * (videos["rife 4.x"] + videos["rife hdv3"])),
                                     "seconds": out["rife 4.x"]["seconds"] + out["rife hdv3"]["seconds"], "note": ""}
    return out


LAST_START = [""]


def iterative(p, label: str, budget: float | None, iters: int | None = None, **overrides) -> dict:
    """`label` on `p` through rngcam.api.reconstruct (the budget counts set-up and solve)."""
    r = reconstruct(p, label, progress=False, time_budget_s=budget, max_iters=iters, log_every_s=1e9, **overrides)
    LAST_START[0] = r.metrics.get("method_settings", {}).get("init_source", "")
    note = "; ".join(e for e in r.metrics["events"] if "stopped" in e or "budget" in e)
    return {**scores(p, r.video), "seconds": r.metrics["seconds"], "iterations": r.metrics["iterations"],
            "note": note.split(":")[0] if note else f"{r.metrics['iterations']} iterations"}


def table(rows: dict[str, dict]) -> list[str]:
    lines = ["| method | PSNR dB | intermediate dB | seconds | |", "|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['psnr']:.2f} | {r['inter']:.2f} | {r['seconds']:.1f} | {r.get('note', '')} |")
    return lines


def rife_speed(size: int) -> dict[str, float]:
    import cv2

    frames = np.load(package_data(SHORT_CLIP))["frames"][[0, 8]].astype(np.float32) / 255
    frames = np.stack([cv2.resize(f, (size, size), interpolation=cv2.INTER_AREA) for f in frames])
    keys = (frames ** 2.2).transpose(3, 0, 1, 2)
    targets = np.linspace(0, 1, 34)[1:-1]
    out = {}
    for model in ("4", "hdv3"):
        for _ in range(2):  # the second run: weights loaded and cached
            t0 = time.perf_counter()
            rife(keys, np.array([0.0, 1.0]), targets, model=model)
            secs = time.perf_counter() - t0
        out[model] = secs / len(targets)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--budget", type=float, default=300.0)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--tv3d-betas", default="1")
    ap.add_argument("--scenes", default="smoke,car,walk,vtest")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--no-ablations", action="store_true", help="Skip pnp's slices=xy and 2-D TV rows on smoke.")
    ap.add_argument("--iters", type=int, default=None,
                    help="Iteration cap instead of a time budget (for a run outside the bench lock; no timings).")
    a = ap.parse_args()
    torch.set_num_threads(1)
    budget = None if a.iters else a.budget
    load = lambda: " ".join(f"{x:.2f}" for x in os.getloadavg())  # noqa: E731
    lines = [f"# pnp and RIFE 4.x against tv3d and the GS-only baselines ({a.size} px)", "",
             f"`bench/pnp_compare.py --budget {a.budget:g}{f' --iters {a.iters}' if a.iters else ''}`: one process, one torch thread, CPU; "
             f"load average at the start {load()}.", ""]
    with tempfile.TemporaryDirectory() as tmp:
        for scene in a.scenes.split(","):
            p = problem(scene, a.size, Path(tmp))
            rows = gs_only(p)
            if scene == "smoke":
                for beta in a.tv3d_betas.split(","):
                    rows[f"tv3d beta {beta}"] = iterative(p, "tv3d", budget, a.iters, beta=float(beta))
            rows["pnp"] = iterative(p, "pnp", budget, a.iters)
            rows["pnp"]["note"] += f" (start: {LAST_START[0]})"
            if scene == "smoke" and not a.no_ablations:
                rows["pnp, frames only (slices=xy)"] = iterative(p, "pnp", budget, a.iters, slices="xy")
                real = ffdnet.load_ffdnet
                ffdnet.load_ffdnet = lambda *_, **__: (_ for _ in ()).throw(ffdnet.DenoiserUnavailableError("hidden"))
                try:
                    rows["pnp, 2-D TV instead of FFDNet"] = iterative(p, "pnp", budget, a.iters)
                finally:
                    ffdnet.load_ffdnet = real
            best_gs = max((r["inter"], n) for n, r in rows.items() if n in GS_ROWS)
            c, k, h, w = p.shape
            lines += [f"## {scene} ({k} frames; load {load()})", "", *table(rows), "",
                      f"pnp - best GS-only ({best_gs[1]}), intermediate frames: {rows['pnp']['inter'] - best_gs[0]:+.2f} dB", ""]
            print("\n".join(lines[-len(rows) - 6:]), flush=True)
    if not a.iters:
        lines += ["## RIFE seconds per interpolated frame", "", "| size | RIFE 4.x | RIFE HDv3 |", "|---|---|---|"]
        for size in (64, 256):
            s = rife_speed(size)
            lines.append(f"| {size} px | {s['4']:.3f} | {s['hdv3']:.3f} |")
    lines += ["", f"load average at the end {load()}", ""]
    text = "\n".join(lines)
    print(text)
    if a.out:
        a.out.write_text(text)


if __name__ == "__main__":
    main()
