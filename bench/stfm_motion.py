"""STFM configurations side by side with the motion yardstick (run by hand, under the bench lock).

    flock /tmp/rngcam-bench.lock .venv/bin/python -m bench.stfm_motion --scenes sineball,smoke,car --size 64 \
        --budget 300 --config 'fast={}' --config 'prior={"preset": "prior"}' --config 'auto={"preset": "auto"}'

Each `--config name=JSON` is a set of STFMSettings overrides; every configuration runs on every
scene for `--budget` seconds (or to its own stop, or `--max-iters`), one after the other in this
process, one torch thread. Printed per run: PSNR all / intermediate, dynamic-region PSNR, on
sineball the ball's centroid error (median / p90 px) and ghost share, the solve time and steps,
and the GS-only baselines (blend, interp, rife, their mean) on the same problem. `--save DIR`
keeps each estimate (float16 .npy) for strips and later metrics; `--json` writes the rows.
At the end it prints the issue's targets (issue 19) for each configuration that ran on their
scenes: sineball's ball centroid, smoke's intermediate PSNR and margin over the best GS-only
video (the GS-only mean included), the real clips' margin over the best GS-only video.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

from rngcam.api import reconstruct
from rngcam.evaluate.scenes import gs_only_video
from rngcam.evaluate.scenes import scene_problem as simulated_problem
from rngcam.recon.metrics import ONE_OBJECT_SCENES, motion_metrics, video_metrics


def scores(video: torch.Tensor, problem, scene: str) -> dict:
    truth = problem.truth.double()
    inter = problem.intermediate_frames()
    out = video_metrics(video.float(), truth.float(), inter)
    out.update(motion_metrics(video.double(), truth, inter, one_object=scene in ONE_OBJECT_SCENES))
    return out


def line(name: str, r: dict) -> str:
    text = f"  {name:14s} {r['psnr_db']:6.2f} / {r.get('psnr_intermediate_db', float('nan')):6.2f} dB, " \
           f"moving {r['psnr_dynamic_db']:6.2f} dB"
    if "centroid_error_median_px" in r:
        text += (f", centroid {r['centroid_error_median_px']:5.2f} / {r['centroid_error_p90_px']:5.2f} px, "
                 f"ghost {r['ghost_median']:.2f}")
    if "solve_s" in r:
        text += f"  [{r['solve_s']:.0f} s, {r['iterations']} steps; {r.get('stop', '')}]"
    return text


TARGETS = {"centroid_median_px": 1.0, "centroid_p90_px": 2.0, "smoke_db": 32.0, "smoke_margin_db": 3.0,
           "clip_margin_db": -0.3, "car_margin_db": 1.5}
CLIP_SCENES = ("car", "walk", "vtest")
GS_ONLY_NAMES = ("blend", "interp", "rife", "gs_mean")


def target_lines(rows: list[dict]) -> list[str]:
    """The issue's targets, one line per (scene, configuration) that ran on a target scene."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        mine = [r for r in rows if r["scene"] == scene]
        gs = [r for r in mine if r["method"] in GS_ONLY_NAMES]
        best = max(gs, key=lambda r: r["psnr_intermediate_db"]) if gs else None
        for r in (r for r in mine if r["method"] not in GS_ONLY_NAMES):
            name, db = f"{scene} {r['method']}", r["psnr_intermediate_db"]
            margin = f"{db - best['psnr_intermediate_db']:+.2f} dB over {best['method']}" if best else "no GS-only rows"
            ok = _met
            if scene == "sineball" and "centroid_error_median_px" in r:
                med, p90 = r["centroid_error_median_px"], r["centroid_error_p90_px"]
                out.append(f"{name}: centroid {med:.2f} / {p90:.2f} px (target <= {TARGETS['centroid_median_px']:g} / "
                           f"<= {TARGETS['centroid_p90_px']:g}: {ok(med <= TARGETS['centroid_median_px'] and p90 <= TARGETS['centroid_p90_px'])}), "
                           f"ghost {r['ghost_median']:.2f}, {db:.2f} dB interm., {margin}")
            elif scene == "smoke":
                gain = db - best["psnr_intermediate_db"] if best else float("nan")
                out.append(f"{name}: {db:.2f} dB interm. (target >= {TARGETS['smoke_db']:g}: {ok(db >= TARGETS['smoke_db'])}), "
                           f"{margin} (target >= +{TARGETS['smoke_margin_db']:g}: {ok(gain >= TARGETS['smoke_margin_db'])}), "
                           f"moving {r['psnr_dynamic_db']:.2f} dB")
            elif scene in CLIP_SCENES and best is not None:
                gain = db - best["psnr_intermediate_db"]
                need = TARGETS["car_margin_db"] if scene == "car" else TARGETS["clip_margin_db"]
                out.append(f"{name}: {db:.2f} dB interm., {margin} (target >= {need:+g}: {ok(gain >= need)})")
    return out


def _met(flag: bool) -> str:
    return "met" if flag else "NOT met"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="sineball,smoke")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--budget", type=float, default=300.0)
    ap.add_argument("--max-iters", type=int)
    ap.add_argument("--config", action="append", default=[], help="name=JSON of STFMSettings overrides")
    ap.add_argument("--no-baselines", action="store_true")
    ap.add_argument("--save", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    configs = {}
    for item in args.config or ["fast={}"]:
        name, _, text = item.partition("=")
        configs[name] = json.loads(text or "{}")
    rows = []
    print(f"load average at start: {os.getloadavg()[0]:.2f}", flush=True)
    for scene in args.scenes.split(","):
        problem, source = simulated_problem(scene, args.size)
        print(f"{scene} {args.size} px ({source}), {problem.shape[1]} frames", flush=True)
        if not args.no_baselines:
            videos = {}
            for name in ("blend", "interp", "rife"):
                try:
                    videos[name] = gs_only_video(name, problem)
                except Exception as exc:  # noqa: BLE001 (a missing optional model is reported, not fatal)
                    print(f"  {name}: not available ({exc})")
            videos["gs_mean"] = np.mean(list(videos.values()), axis=0)
            for name, video in videos.items():
                r = {"scene": scene, "method": name, **scores(torch.from_numpy(np.asarray(video)), problem, scene)}
                rows.append(r)
                print(line(name, r), flush=True)
        for name, overrides in configs.items():
            res = reconstruct(problem, "stfm", progress=False, time_budget_s=args.budget, max_iters=args.max_iters,
                              log_every_s=args.budget, **overrides)
            video = torch.from_numpy(res.video).double()
            stop = next((e for e in res.metrics["events"] if e.startswith("stopped")), "budget")
            r = {"scene": scene, "method": name, "settings": overrides, "setup_s": res.metrics["setup_seconds"],
                 "solve_s": res.metrics["seconds"], "iterations": res.metrics["iterations"], "stop": stop[:120],
                 "load": os.getloadavg()[0], "notes": [f"{a}: {b}" for a, b in res.left_out] + list(res.notes),
                 **scores(video, problem, scene)}
            rows.append(r)
            print(line(name, r), flush=True)
            for note in res.notes:
                print(f"    note: {note}", flush=True)
            if args.save is not None:
                args.save.mkdir(parents=True, exist_ok=True)
                np.save(args.save / f"{scene}{args.size}_{name}.npy", video.numpy().astype(np.float16))
    print(f"load average at end: {os.getloadavg()[0]:.2f}", flush=True)
    print("Targets (issue 19):")
    for text in target_lines(rows):
        print("  " + text, flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
