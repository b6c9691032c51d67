"""The STFM `paper` preset run towards its plateau (long, unattended; not part of the tests).

    nice -n 19 .venv/bin/python -m bench.paper_convergence run --scenes sineball,smoke --size 32 \
        --until 2026-11-23T17:15 --work /tmp/rngcam-paper
    .venv/bin/python -m bench.paper_convergence report --work /tmp/rngcam-paper --out bench/paper_convergence.md
    flock /tmp/rngcam-bench.lock .venv/bin/python -m bench.paper_convergence timing --work /tmp/rngcam-paper \
        --scenes sineball,smoke --fast 'sineball=auto,smoke=auto'

`run` fits the paper preset (SIREN fields as published, Adam 5e-6, fixed iterations: no stop
test) on each scene in turn, one torch thread. Fit time is the process's CPU time in the steps
(`cpu_s`; a niced run on a busy machine waits for the CPU, and wall time would count the wait), and
the plateau is judged over steps. Every `--log-every` seconds of fit time it logs
PSNR (all and intermediate frames) and the dynamic-region PSNR (rngcam.recon.metrics.psnr_dynamic)
to `<work>/<scene>/log.jsonl`; every `--save-every` seconds it checkpoints the method's state
and saves the estimate (float16 .npy), so the curve can be recomputed with other metrics and a
later run resumes where this one stopped. The scenes share the time up to `--until` equally
(a scene already further along gets what it has left). `report` turns the logs into a table and
says whether each curve has plateaued (dynamic PSNR up by less than 0.1 dB over its last third).
`timing` (under the bench lock: it measures time) measures the paper preset's CPU seconds per step
on the same problem, and the CPU time (set-up included, evaluations excluded) a fast preset takes
to reach the paper preset's best logged dynamic PSNR: the fast-against-paper time ratio.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from rngcam.evaluate.scenes import scene_problem as simulated_problem
from rngcam.recon import registry
from rngcam.recon.checkpoint import plain
from rngcam.recon.metrics import motion_metrics, video_metrics
from rngcam.recon.runner import method_view

PLATEAU_DB = 0.1  # dynamic PSNR gained over the last third of the run below this: plateaued
ONE_OBJECT = {"sineball"}


def evaluate(method, problem) -> dict:
    video = method.estimate().detach().double().cpu()
    truth = problem.truth.double()
    inter = problem.intermediate_frames()
    out = video_metrics(video.float(), truth.float(), inter)
    out.update(motion_metrics(video, truth, inter, one_object=problem_scene(problem) in ONE_OBJECT))
    return out


def problem_scene(problem) -> str:
    return getattr(problem, "_bench_scene", "")


def run_scene(scene: str, size: int, work: Path, deadline: float, log_every: float, save_every: float) -> None:
    folder = work / scene
    folder.mkdir(parents=True, exist_ok=True)
    problem, source = simulated_problem(scene, size)
    problem._bench_scene = scene
    stfm = registry.get("stfm")
    method = stfm.factory(method_view(problem), stfm.settings("paper"))
    ckpt, log_path = folder / "checkpoint.pt", folder / "log.jsonl"
    fit_s, cpu_s = 0.0, 0.0
    if ckpt.is_file():
        saved = torch.load(ckpt, weights_only=True)  # data only (checkpoint.plain on save)
        method.load_state_dict(saved["method"])
        fit_s, cpu_s = saved["fit_s"], saved.get("cpu_s", math.nan)
        torch.set_rng_state(saved["rng"])
        print(f"{scene}: resumed at step {method.steps}, {fit_s:.0f} s of fit", flush=True)
    else:
        meta = {"scene": scene, "size": size, "source": source, "settings": method.resolved_settings()}
        (folder / "meta.json").write_text(json.dumps(meta, indent=1, default=str))
        with log_path.open("a") as f:
            f.write(json.dumps({"step": 0, "fit_s": 0.0, "cpu_s": 0.0, **evaluate(method, problem)}) + "\n")
    clock = 0.0  # CPU seconds since this process started fitting (the log and checkpoint cadence)
    next_log, next_save = log_every, save_every
    while time.time() < deadline:
        t0, c0 = time.perf_counter(), time.process_time()
        method.step()
        fit_s += time.perf_counter() - t0
        used = time.process_time() - c0
        cpu_s += used
        clock += used
        if clock >= next_log or time.time() >= deadline:
            row = {"step": method.steps, "fit_s": fit_s, "cpu_s": cpu_s,
                   "wall_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                   **evaluate(method, problem)}
            with log_path.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"{scene} step {row['step']} cpu {cpu_s:.0f} s: PSNR {row['psnr_db']:.2f} dB, "
                  f"dynamic {row['psnr_dynamic_db']:.2f} dB", flush=True)
            next_log = clock + log_every
        if clock >= next_save or time.time() >= deadline:
            tmp = ckpt.with_name(f".{ckpt.name}.{os.getpid()}.partial")
            torch.save(plain({"method": method.state_dict(), "fit_s": fit_s, "cpu_s": cpu_s,
                              "rng": torch.get_rng_state()}), tmp)
            os.replace(tmp, ckpt)
            np.save(folder / f"estimate_{method.steps:08d}.npy",
                    method.estimate().detach().cpu().numpy().astype(np.float16))
            next_save = clock + save_every


def read_log(folder: Path) -> list[dict]:
    path = folder / "log.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def plateau(rows: list[dict]) -> tuple[str, float]:
    """("plateaued" / "still rising", dynamic dB gained over the last third of the steps)."""
    if len(rows) < 3:
        return "too short", math.nan
    end = rows[-1]["step"]
    before = [r for r in rows if r["step"] <= 2 * end / 3][-1]
    gain = rows[-1]["psnr_dynamic_db"] - before["psnr_dynamic_db"]
    return ("plateaued" if gain < PLATEAU_DB else "still rising"), gain


def report(work: Path, out: Path | None) -> str:
    lines = ["# STFM paper preset towards its plateau (bench/paper_convergence.py)", ""]
    for folder in sorted(p for p in work.iterdir() if p.is_dir()):
        rows = read_log(folder)
        if not rows:
            continue
        meta = json.loads((folder / "meta.json").read_text()) if (folder / "meta.json").is_file() else {}
        state, gain = plateau(rows)
        best = max(rows, key=lambda r: r["psnr_dynamic_db"])
        lines += [f"## {folder.name}, {meta.get('size', '?')} px ({meta.get('source', '?')})", "",
                  f"{rows[-1]['step']} steps in {rows[-1]['fit_s']:.0f} s of wall-clock fit: {state} "
                  f"(dynamic PSNR {gain:+.2f} dB over the last third of the steps); best dynamic PSNR "
                  f"{best['psnr_dynamic_db']:.2f} dB at step {best['step']}.", "",
                  "| wall s | CPU s | step | PSNR all | PSNR interm. | PSNR dynamic | centroid med / p90 px | ghost med |",
                  "|---|---|---|---|---|---|---|---|"]
        picks = _spread(rows, 16)
        for r in picks:
            cen = (f"{r['centroid_error_median_px']:.2f} / {r['centroid_error_p90_px']:.2f}"
                   if "centroid_error_median_px" in r else "-")
            ghost = f"{r['ghost_median']:.2f}" if "ghost_median" in r else "-"
            lines.append(f"| {r['fit_s']:.0f} | {r.get('cpu_s', math.nan):.0f} | {r['step']} | {r['psnr_db']:.2f} | "
                         f"{r.get('psnr_intermediate_db', math.nan):.2f} | {r['psnr_dynamic_db']:.2f} | {cen} | {ghost} |")
        lines.append("")
    text = "\n".join(lines)
    if out is not None:
        out.write_text(text)
    return text


def _spread(rows: list[dict], n: int) -> list[dict]:
    """About n rows spread over the steps, denser early (the first and last included)."""
    if len(rows) <= n:
        return rows
    end, picks, seen = rows[-1]["step"], [], set()
    for i in range(n):
        target = end * (i / (n - 1)) ** 2  # denser early, where the curve moves
        j = min(range(len(rows)), key=lambda k: abs(rows[k]["step"] - target))
        if j not in seen:
            seen.add(j)
            picks.append(rows[j])
    return picks


def paper_step_cpu_s(problem, steps: int) -> float:
    """CPU seconds per step of the paper preset on `problem` (fresh fields: a step's cost does
    not depend on the weights)."""
    stfm = registry.get("stfm")
    method = stfm.factory(method_view(problem), stfm.settings("paper"))
    method.step()  # warm-up (first-call allocations)
    c0 = time.process_time()
    for _ in range(steps):
        method.step()
    return (time.process_time() - c0) / steps


def fast_cpu_to_reach(problem, preset: str, target_db: float, max_cpu_s: float, every: int = 10) -> dict:
    """CPU seconds (set-up included, evaluations excluded) until `preset`'s dynamic PSNR reaches
    target_db (checked every `every` steps), or the best it reached within max_cpu_s."""
    c0 = time.process_time()
    stfm = registry.get("stfm")
    method = stfm.factory(method_view(problem), stfm.settings(preset))
    cpu = time.process_time() - c0
    best, steps = -math.inf, 0
    while True:
        score = evaluate(method, problem)["psnr_dynamic_db"]
        best = max(best, score)
        if score >= target_db or cpu >= max_cpu_s or method.converged():
            return {"preset": preset, "reached": score >= target_db, "cpu_s": cpu, "steps": steps,
                    "psnr_dynamic_db": score, "best_db": best}
        c0 = time.process_time()
        for _ in range(every):
            method.step()
        cpu += time.process_time() - c0
        steps += every


def timing(work: Path, scenes: list[str], fast: dict[str, str], steps: int, max_cpu_s: float) -> str:
    lines = [f"load average at start: {os.getloadavg()[0]:.2f}"]
    for scene in scenes:
        rows = read_log(work / scene)
        if not rows:
            lines.append(f"{scene}: no paper-preset log in {work / scene}")
            continue
        meta = json.loads((work / scene / "meta.json").read_text())
        problem, _ = simulated_problem(scene, meta["size"])
        problem._bench_scene = scene
        best = max(rows, key=lambda r: r["psnr_dynamic_db"])
        per_step = paper_step_cpu_s(problem, steps)
        paper_cpu = best["step"] * per_step
        state, gain = plateau(rows)
        got = fast_cpu_to_reach(problem, fast.get(scene, "fast"), best["psnr_dynamic_db"], max_cpu_s)
        verdict = (f"reached it after {got['cpu_s']:.1f} CPU s ({got['steps']} steps): ratio "
                   f"{got['cpu_s'] / paper_cpu:.4f}" if got["reached"] else
                   f"did not reach it within {got['cpu_s']:.0f} CPU s (best {got['best_db']:.2f} dB)")
        lines.append(f"{scene} {meta['size']} px: paper preset {per_step:.3f} CPU s/step ({steps} steps timed); "
                     f"its best dynamic PSNR {best['psnr_dynamic_db']:.2f} dB at step {best['step']} = "
                     f"{paper_cpu:.0f} CPU s ({state}, {gain:+.2f} dB over the last third); "
                     f"preset {got['preset']} {verdict}")
        print(lines[-1], flush=True)
    lines.append(f"load average at end: {os.getloadavg()[0]:.2f}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--scenes", default="sineball,smoke")
    r.add_argument("--size", type=int, default=32)
    r.add_argument("--until", required=True, help="UTC deadline, ISO format (e.g. 2026-11-23T17:15)")
    r.add_argument("--work", type=Path, required=True)
    r.add_argument("--log-every", type=float, default=60.0, help="seconds of fit between log rows")
    r.add_argument("--save-every", type=float, default=600.0, help="seconds of fit between checkpoints")
    s = sub.add_parser("report")
    s.add_argument("--work", type=Path, required=True)
    s.add_argument("--out", type=Path)
    t = sub.add_parser("timing")
    t.add_argument("--work", type=Path, required=True)
    t.add_argument("--scenes", default="sineball,smoke")
    t.add_argument("--fast", default="sineball=auto,smoke=auto", help="scene=preset pairs for the fast path")
    t.add_argument("--steps", type=int, default=100, help="paper-preset steps timed")
    t.add_argument("--max-cpu", type=float, default=300.0, help="CPU seconds the fast path may take")
    args = ap.parse_args()
    if args.cmd == "timing":
        torch.set_num_threads(1)
        fast = dict(item.split("=") for item in args.fast.split(",") if item)
        print(timing(args.work, args.scenes.split(","), fast, args.steps, args.max_cpu))
        return
    if args.cmd == "report":
        print(report(args.work, args.out))
        return
    torch.set_num_threads(1)
    deadline = dt.datetime.fromisoformat(args.until).replace(tzinfo=dt.timezone.utc).timestamp()
    scenes = args.scenes.split(",")
    for i, scene in enumerate(scenes):
        share = (deadline - time.time()) / (len(scenes) - i)
        run_scene(scene, args.size, args.work, min(deadline, time.time() + share), args.log_every, args.save_every)


if __name__ == "__main__":
    main()
