"""Side-by-side benchmark of STFM against the baselines, run by hand (not part of the tests).

    .venv/bin/python -m bench.stfm_compare --budget 200 --out bench/stfm_compare.md

In one process on the CPU, under the same time budget per iterative method:
1. STFM fast (the default: three fits on different GS-only starts, averaged, then refined), STFM single
   (`dynamic_base="video"`: one fit on the RIFE video), tv3d, blend, interp, rife and gs_mean (the plain
   average of the three GS-only videos, a GS-only ensemble) on `sineball`, `smoke` and the three real clips
   (`car`, `walk`, `vtest`: bikes_car_256, bikes_walk_256, vtest_256 at span 8) at 64x64, STFM
   paper on sineball, smoke and car; STFM fast, single and the GS-only baselines also at 128x128;
2. on `smoke` at 64x64: STFM fast with all components against the four ablations
   (no_static, no_motion_reg, no_rs, no_gs); and STFM fast with `--seeds` seeds (the fields'
   initialisation and the sampling of rows and frames; the measurement stays the same), against
   tv3d and the best GS-only baseline on that problem: one seed's margin is one draw; and tv3d
   with each temporal weight in `--tv3d-betas`, the best chosen by the truth (the most
   favourable setting for tv3d), with STFM fast's margin over it;
3. the time the fast preset needs to reach the paper preset's final PSNR, as a ratio of the
   paper preset's run time;
4. peak memory of an STFM fit at K and 2K frames (the same scene on a grid with half the
   frame duration): peak resident set size (VmHWM from /proc/self/status) of a fresh
   subprocess per K, which sees torch's CPU allocations (tracemalloc does not); also its
   growth over the peak just before the fit starts (interpreter, torch and the problem),
   which is what the fit adds. The problems are built by the parent and loaded by the children;
5. for every run (and, when the main table did not run, for smoke's): what each measurement sees
   of its remaining error, ||A (estimate - truth)|| over the noise norm ||A truth - b||.

Problems come from `rngcam.sim.simulate` (the bundle path) when it exists, else from an
equivalent in-process simulation (same timing; Gaussian noise) - the report says which.
PSNR is over all frames / over the intermediate frames (away from the GS key frames); in brackets the
moving-region PSNR (psnr_dynamic_db) and, on sineball, the ball's centroid error median / p90 and ghost share.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]

from rngcam.api import reconstruct
from rngcam.evaluate.scenes import gs_only_video, inline_problem
from rngcam.evaluate.scenes import scene_problem as simulated_problem
from rngcam.recon import registry
from rngcam.recon.metrics import ONE_OBJECT_SCENES, error_visibility, motion_metrics, video_metrics
from rngcam.recon.problem import Problem

GS_ONLY = registry.labels(registry.GS_ONLY)


def run_gs_only(name: str, p: Problem) -> dict:
    t0 = time.perf_counter()
    try:
        video = gs_only_video(name, p)
    except Exception as exc:  # noqa: BLE001 (a missing optional model must not stop the benchmark)
        return {"error": f"{type(exc).__name__}: {exc}"}
    secs = time.perf_counter() - t0
    video = torch.from_numpy(video)
    m = {**video_metrics(video, p.truth.float(), p.intermediate_frames()), **motion_of(video, p)}
    return {**m, "setup_s": 0.0, "solve_s": secs, "iterations": 1, "log": [],
            "visibility": error_visibility(p, video)}


def run_iterative(name: str, p: Problem, budget_s: float, opts: dict | None = None,
                  max_iters: int | None = None) -> dict:
    """A registry label or one of this script's VARIANTS (with `opts` on top) through
    rngcam.api.reconstruct for `budget_s` seconds, set-up included (and at most `max_iters`
    iterations); PSNR logged against solve time."""
    label, base = VARIANTS.get(name, (name, {}))
    try:
        r = reconstruct(p, label, progress=False, time_budget_s=budget_s, max_iters=max_iters,
                        log_every_s=max(budget_s / 20, 0.5), threads=torch.get_num_threads(), **base, **(opts or {}))
    except ImportError as exc:
        return {"error": f"not available: {exc}"}
    m = r.metrics
    out = {k: m[k] for k in ("psnr_db", "psnr_intermediate_db", "ssim") if k in m}
    video = torch.from_numpy(r.video)
    out.update(setup_s=m.get("setup_seconds", 0.0), solve_s=m["seconds"], iterations=m["iterations"],
               log=[(row["solve_s"], row.get("psnr_db")) for row in r.log], status=r.status,
               stopped=any(e.startswith("stopped at") for e in m["events"]),
               visibility=error_visibility(p, video), **motion_of(video, p))
    out["left_out"] = [c for c, _ in r.left_out if c not in {a for a, _ in p.left_out}]
    return out


# ----------------------------------------------------------------------------- memory


def peak_rss_mib() -> float:
    """This process's peak resident set size (VmHWM). Unlike ru_maxrss it does not inherit the
    parent's high-water mark across fork + exec."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def problem_data(p) -> dict:
    """A Problem as tensors and plain values (what torch.load(weights_only=True) reads back)."""
    import dataclasses

    out = {}
    for f in dataclasses.fields(p):
        v = getattr(p, f.name)
        if f.name == "grid":
            v = {"dt_s": v.dt_s, "n_frames": v.n_frames}
        elif isinstance(v, np.ndarray):
            v = torch.from_numpy(v)
        out[f.name] = v
    return out


def problem_from_data(d: dict):
    """The Problem `problem_data` stored."""
    from rngcam.physics.timing import VideoGrid
    from rngcam.recon.problem import Problem

    return Problem(**{**d, "grid": VideoGrid(**d["grid"]), "gs_times_s": d["gs_times_s"].numpy()})


def memory_child(problem_path: str, steps: int) -> None:
    """Run in a fresh process: print JSON with RSS before the fit and the peak RSS (MiB) over
    `steps` steps, or (steps 0) the whole fit to its own stop (the ensemble's refinement included)."""
    p = problem_from_data(torch.load(problem_path, weights_only=True))
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # import the optimiser machinery first
    before = peak_rss_mib()
    r = reconstruct(p, "stfm-fast", progress=False, max_iters=steps or None, time_budget_s=None if steps else 1e6,
                    threads=torch.get_num_threads())
    done = r.metrics["iterations"]
    peak = peak_rss_mib()
    print(json.dumps({"frames": p.grid.n_frames, "before_mib": before, "peak_mib": peak, "steps": done,
                      "refined": r.metrics.get("method_results", {}).get("refine_steps") is not None}))


def measure_memory(scene: str, size: int, steps: int) -> list[dict]:
    """Problems are built here and loaded by the children, so that reading the PSF file does not
    set the children's high-water mark."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for factor in (1, 2):
            path = Path(tmp) / f"problem{factor}.pt"
            torch.save(problem_data(inline_problem(scene, size, dt_factor=factor)), path)
            cmd = [sys.executable, __file__, "--memory-child", str(path), str(steps)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return rows


# ----------------------------------------------------------------------------- report


def motion_of(video: torch.Tensor, p: Problem) -> dict:
    """The motion yardstick (rngcam.recon.metrics.motion_metrics) over the intermediate frames."""
    one = getattr(p, "bench_scene", "") in ONE_OBJECT_SCENES
    return motion_metrics(video.double(), p.truth.double(), p.intermediate_frames(), one_object=one)


def fmt(r: dict) -> str:
    """PSNR all / intermediate, [moving-region PSNR; on sineball, centroid median / p90 px, ghost]."""
    if "error" in r:
        return "n/a"
    text = f"{r['psnr_db']:.2f} / {r.get('psnr_intermediate_db', float('nan')):.2f}"
    if "psnr_dynamic_db" in r:
        text += f" [{r['psnr_dynamic_db']:.2f}"
        if "centroid_error_median_px" in r:
            text += (f"; {r['centroid_error_median_px']:.1f} / {r['centroid_error_p90_px']:.1f} px, "
                     f"ghost {r['ghost_median']:.2f}")
        text += "]"
    return text


# Registry labels, this script's variants of them, and gs_mean (the average of the GS-only videos).
VARIANTS = {"stfm-single": ("stfm-fast", {"dynamic_base": "video"})}
METHODS = ("stfm-fast", "stfm-prior", "stfm-single", "stfm-paper", "tv3d", "blend", "interp", "rife", "gs_mean")

# The targets on intermediate frames: STFM fast minus the best GS-only baseline / tv3d.
GS_TARGETS = {"smoke": 3.0, "car": 1.5, "walk": -0.3, "vtest": -0.3}
TV_TARGETS = {"smoke": 6.0}


def verdict(gain: float, target: float | None) -> str:
    return "" if target is None else f" (target {target:+.1f}: {'met' if gain >= target else 'NOT met'})"


def ablation_order(db: dict[str, float | None]) -> str:
    """The paper's order on smoke, full > no_static > no_rs and no_gs > no_motion_reg, against `db`
    (intermediate PSNR per variant): met, or which of its steps fail."""
    if any(db.get(k) is None for k in ("full", "no_static", "no_rs", "no_gs", "no_motion_reg")):
        return "Paper's ablation order: not measured (a variant failed)."
    steps = [("full", "no_static"), ("no_static", "no_rs"), ("no_static", "no_gs"),
             ("no_rs", "no_motion_reg"), ("no_gs", "no_motion_reg")]
    failed = [f"{a} {db[a]:.2f} <= {b} {db[b]:.2f}" for a, b in steps if not db[a] > db[b]]
    ours = " > ".join(sorted(db, key=db.get, reverse=True))
    return (f"Paper's ablation order (full > no_static > no_rs and no_gs > no_motion_reg): "
            f"{'met' if not failed else 'NOT met (' + '; '.join(failed) + ')'}; ours: {ours}.")


def time_to_reach(log: list[tuple[float, float]], target: float) -> float | None:
    for t, value in log:
        if value is not None and value >= target:
            return t
    return None


def reuse_or_run(results: dict, key: tuple, label: str, run_fn) -> dict:
    """results[key] when an earlier part ran it, else run_fn() (printed and stored for later parts)."""
    r = results.get(key)
    if r is None:
        print(label, flush=True)
        r = results[key] = run_fn()
        print("   ", fmt(r), r.get("error", ""), flush=True)
    return r


def smoke_run(args, results: dict, p: Problem, size: int, name: str, part: str) -> dict:
    """Method `name` of the main table on smoke at `size`: its main-table run when there was one."""
    if name in (*GS_ONLY, "gs_mean"):
        def run_fn():
            return run_gs_only(name, p)
    else:
        def run_fn():
            return run_iterative(name, p, args.budget, max_iters=args.max_iters)
    return reuse_or_run(results, ("smoke", size, name), f"[{part}] {name}", run_fn)


def seed_spread(args, results: dict) -> list[str]:
    """STFM fast on smoke with seeds 0..args.seeds-1; tv3d and the GS-only baselines from the main
    table when it ran, else run here."""
    size = int(args.sizes.split(",")[0])
    p, _ = simulated_problem("smoke", size)
    ref = {}
    for name in ("tv3d", *GS_ONLY):
        r = smoke_run(args, results, p, size, name, "seeds")
        if "error" not in r:
            ref[name] = r["psnr_intermediate_db"]
    gs_best = max((ref[n] for n in GS_ONLY if n in ref), default=math.nan)
    lines = ["", f"## Seed spread: STFM fast on smoke {size}x{size} (intermediate-frame PSNR)", "",
             ("The same measurement each time; the seed sets the fields' initialisation and the sampling of "
              f"rows and frames. tv3d {ref.get('tv3d', math.nan):.2f} dB, best GS-only {gs_best:.2f} dB."), "",
             "| seed | PSNR all / intermediate | iterations | stopped | - tv3d | - best GS-only |",
             "|---|---|---|---|---|---|"]
    values = []
    for seed in range(args.seeds):
        key = ("smoke", size, "stfm-fast") if seed == 0 else ("smoke", size, f"stfm-fast seed {seed}")
        r = reuse_or_run(results, key, f"[seeds] stfm-fast seed {seed}",
                         lambda seed=seed: run_iterative("stfm-fast", p, args.budget, {"seed": seed},
                                                         args.max_iters))
        if "error" in r:
            continue
        value = r["psnr_intermediate_db"]
        values.append(value)
        lines.append(f"| {seed} | {fmt(r)} | {r['iterations']} | {'yes' if r.get('stopped') else '-'} | "
                     f"{value - ref.get('tv3d', math.nan):+.2f} | {value - gs_best:+.2f} |")
    if values:
        mean = float(np.mean(values))
        results["seeds_mean"] = mean
        lines += ["", (f"Mean {mean:.2f} dB (min {min(values):.2f}, max {max(values):.2f}, sd {np.std(values):.2f}): "
                       f"mean margin over tv3d {mean - ref.get('tv3d', math.nan):+.2f} dB"
                       f"{verdict(mean - ref.get('tv3d', math.nan), TV_TARGETS['smoke'])}, over the best GS-only "
                       f"{mean - gs_best:+.2f} dB{verdict(mean - gs_best, GS_TARGETS['smoke'])}.")]
    return lines


def tv3d_beta(args, results: dict) -> list[str]:
    """tv3d on smoke with each temporal weight beta in args.tv3d_betas, scored by the truth: the most
    favourable beta for tv3d (an oracle; a sweep scored on held-out RS rows can only do as well or
    worse), and STFM fast's margin over it (seed 0 and, when the seeds part ran, the seeds' mean)."""
    from rngcam.recon.methods.tv3d import TV3DSettings

    size = int(args.sizes.split(",")[0])
    p, _ = simulated_problem("smoke", size)
    default_beta = TV3DSettings().beta
    lines = ["", f"## tv3d's temporal weight on smoke {size}x{size} (intermediate-frame PSNR)", "",
             (f"tv3d with each beta (the default is {default_beta:g}; tau stays at its default) for the same budget, "
              "scored by the truth: the best row is the most favourable beta for tv3d, an oracle that a sweep on "
              "held-out RS rows (`rngcam sweep`) can at best match."), "",
             "| beta | PSNR all / intermediate | iterations |", "|---|---|---|"]
    scores = {}
    for beta in (float(b) for b in args.tv3d_betas.split(",")):
        key = ("smoke", size, "tv3d") if beta == default_beta else ("smoke", size, f"tv3d beta {beta:g}")
        r = reuse_or_run(results, key, f"[tv3d beta] {beta:g}",
                         lambda beta=beta: run_iterative("tv3d", p, args.budget, {"beta": beta}, args.max_iters))
        if "error" in r:
            continue
        scores[beta] = r["psnr_intermediate_db"]
        lines.append(f"| {beta:g} | {fmt(r)} | {r['iterations']} |")
    fast = smoke_run(args, results, p, size, "stfm-fast", "tv3d beta")
    if scores and "error" not in fast:
        best = max(scores, key=scores.get)
        gain = fast["psnr_intermediate_db"] - scores[best]
        text = (f"Best beta {best:g} ({scores[best]:.2f} dB). STFM fast - tv3d at that beta: {gain:+.2f} dB at seed 0"
                f"{verdict(gain, TV_TARGETS['smoke'])}")
        if "seeds_mean" in results:
            mean_gain = results["seeds_mean"] - scores[best]
            text += f"; {mean_gain:+.2f} dB on the seeds' mean{verdict(mean_gain, TV_TARGETS['smoke'])}"
        lines += ["", text + "."]
    return lines


def visibility(args, results: dict) -> list[str]:
    """What each measurement sees of each method's remaining error, in units of its noise, on smoke
    at the first size (and on every scene the main table ran): below 1 the error hides under the
    noise, so only a better prior, not a closer fit, can remove it."""
    size = int(args.sizes.split(",")[0])
    p, _ = simulated_problem("smoke", size)
    for name in ("stfm-fast", "tv3d", *GS_ONLY):
        smoke_run(args, results, p, size, name, "visibility")
    lines = ["", "## What the measurements see of the remaining error", "",
             ("||A (estimate - truth)|| over the noise norm ||A truth - b||, per sensor. Below 1 the error hides "
              "under the measurement's noise: a closer fit to the data cannot find it, only a better prior can."), "",
             "| scene | size | method | PSNR all / intermediate | RS: error / noise | GS: error / noise |",
             "|---|---|---|---|---|---|"]
    for key, r in results.items():
        if not isinstance(key, tuple) or "visibility" not in r:
            continue
        scene, size, name = key
        seen = r["visibility"]
        lines.append(f"| {scene} | {size} | {name} | {fmt(r)} | {seen.get('rs', math.nan):.2f} | "
                     f"{seen.get('gs', math.nan):.2f} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=float, default=60.0, help="seconds per iterative method")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "stfm_compare.md")
    ap.add_argument("--scenes", default="sineball,smoke,car,walk,vtest")
    ap.add_argument("--paper-scenes", default="sineball,smoke,car", help="scenes that also run the paper preset")
    ap.add_argument("--paper-budget", type=float, default=None,
                    help="seconds for the paper preset [--budget] (it needs hours; a long run gives an honest "
                         "time-to-equal-PSNR ratio)")
    ap.add_argument("--sizes", default="64,128")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (1: two benches can share 2 cores; oversubscribed threads ran 6-60x slower)")
    ap.add_argument("--methods", default=",".join(METHODS), help="methods of the main table")
    ap.add_argument("--max-iters", type=int, default=None,
                    help="also stop iterative methods after this many iterations (with a long --budget: "
                         "run each to its own stop)")
    ap.add_argument("--seeds", type=int, default=5, help="STFM fast seeds on smoke (the 'seeds' part)")
    ap.add_argument("--tv3d-betas", default="1,10,30,100",
                    help="tv3d temporal weights tried on smoke (the 'tv3d_beta' part)")
    ap.add_argument("--skip", default="",
                    help="comma-separated parts to skip: main,ablation,seeds,tv3d_beta,visibility,memory")
    ap.add_argument("--memory-child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.memory_child:
        memory_child(args.memory_child[0], int(args.memory_child[1]))
        return
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # pay torch.optim's first-use import here
    skip = set(filter(None, args.skip.split(",")))
    scenes = args.scenes.split(",")
    sizes = [int(s) for s in args.sizes.split(",")]
    cap = f", at most {args.max_iters} iterations" if args.max_iters else ""
    lines = [(f"# STFM benchmark ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, "
             f"{torch.get_num_threads()} threads, budget {args.budget:g} s per iterative method{cap})"), ""]
    results: dict = {}
    sources = set()
    if "main" not in skip:
        methods = [m for m in METHODS if m in args.methods.split(",")]
        for size in sizes:
            for scene in scenes:
                p, source = simulated_problem(scene, size)
                sources.add(source)
                for name in methods:
                    if size > 64 and name in ("stfm-paper", "tv3d"):
                        continue
                    if name == "stfm-paper" and scene not in args.paper_scenes.split(","):
                        continue
                    print(f"[{scene} {size}] {name}", flush=True)
                    if name in (*GS_ONLY, "gs_mean"):
                        r = run_gs_only(name, p)
                    else:
                        budget = args.paper_budget if name == "stfm-paper" and args.paper_budget else args.budget
                        r = run_iterative(name, p, budget, max_iters=args.max_iters)
                    results[(scene, size, name)] = r
                    print("   ", fmt(r), r.get("error", ""), flush=True)
        lines += ["## PSNR (dB): all frames / intermediate frames", "",
                  (f"Problems: {', '.join(sorted(sources))}. Iterative methods: setup, then "
                  f"{args.budget:g} s of the shared loop (setup time in the second table)."), "",
                  "| scene | size | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
        for size in sizes:
            for scene in scenes:
                cells = [fmt(results[(scene, size, n)]) if (scene, size, n) in results else "-" for n in methods]
                lines.append(f"| {scene} | {size} | " + " | ".join(cells) + " |")
        lines += ["", ("Scenes car, walk and vtest are the real clips bikes_car_256, bikes_walk_256 and vtest_256 "
                       "at --span 8. 'stopped' = ended before the budget by its own stop (RS residual at the noise level, or stalled)."), "",
                  "| scene | size | method | setup s | solve s | iterations | stopped | left out |",
                  "|---|---|---|---|---|---|---|---|"]
        for (scene, size, name), r in results.items():
            if "error" in r:
                lines.append(f"| {scene} | {size} | {name} | {r['error']} | | | | |")
            elif name not in (*GS_ONLY, "gs_mean"):
                lines.append(f"| {scene} | {size} | {name} | {r['setup_s']:.1f} | {r['solve_s']:.1f} | "
                             f"{r['iterations']} | {'yes' if r.get('stopped') else '-'} | "
                             f"{', '.join(r.get('left_out', [])) or '-'} |")
        lines += ["", "## Targets (intermediate-frame PSNR)", ""]
        for size in sizes:
            for scene in scenes:
                fast = results.get((scene, size, "stfm-fast"))
                gs_best = max((results[(scene, size, n)].get("psnr_intermediate_db", -math.inf)
                               for n in GS_ONLY if (scene, size, n) in results
                               and "error" not in results[(scene, size, n)]), default=None)
                tv = results.get((scene, size, "tv3d"))
                if fast and "error" not in fast and gs_best is not None:
                    gain = fast['psnr_intermediate_db'] - gs_best
                    msg = f"- {scene} {size}: STFM fast - best GS-only = {gain:+.2f} dB{verdict(gain, GS_TARGETS.get(scene))}"
                    if tv and "error" not in tv:
                        gain = fast['psnr_intermediate_db'] - tv['psnr_intermediate_db']
                        msg += f"; STFM fast - tv3d = {gain:+.2f} dB{verdict(gain, TV_TARGETS.get(scene))}"
                    mean = results.get((scene, size, "gs_mean"))
                    if mean and "error" not in mean:
                        msg += f"; STFM fast - GS-only mean = {fast['psnr_intermediate_db'] - mean['psnr_intermediate_db']:+.2f} dB"
                    single = results.get((scene, size, "stfm-single"))
                    if single and "error" not in single:
                        msg += f" (STFM single - best GS-only = {single['psnr_intermediate_db'] - gs_best:+.2f} dB)"
                    lines.append(msg)
        if any(name == "stfm-paper" for _, _, name in results):
            lines += ["", "## Fast preset: time to reach the paper preset's final PSNR", ""]
        for scene in scenes:
            fast, paper = results.get((scene, sizes[0], "stfm-fast")), results.get((scene, sizes[0], "stfm-paper"))
            if not fast or not paper or "error" in fast or "error" in paper:
                continue
            t = time_to_reach(fast["log"], paper["psnr_db"])
            paper_total = paper["setup_s"] + paper["solve_s"]
            if t is None:
                lines.append(f"- {scene}: fast never reached {paper['psnr_db']:.2f} dB")
            else:
                total = fast["setup_s"] + t
                lines.append(f"- {scene}: paper {paper['psnr_db']:.2f} dB after {paper_total:.1f} s; fast reached it "
                             f"after {total:.1f} s (setup {fast['setup_s']:.1f} + solve {t:.1f}): "
                             f"ratio {total / paper_total:.3f}")
    if "ablation" not in skip:
        p, source = simulated_problem("smoke", sizes[0])
        lines += ["", f"## Ablations on smoke {sizes[0]}x{sizes[0]} (STFM fast, components='all')", "",
                  "| variant | PSNR all / intermediate | iterations |", "|---|---|---|"]
        ablations: dict[str, float | None] = {}
        for flag in ("full", "no_static", "no_motion_reg", "no_rs", "no_gs"):
            opts = {"components": "all"} | ({flag: True} if flag != "full" else {})
            print(f"[ablation] {flag}", flush=True)
            r = run_iterative("stfm-fast", p, args.budget, opts)
            print("   ", fmt(r), flush=True)
            lines.append(f"| {flag} | {fmt(r)} | {r.get('iterations', '-')} |")
            ablations[flag] = r.get("psnr_intermediate_db")
        lines += ["", ablation_order(ablations)]
    if "seeds" not in skip:
        lines += seed_spread(args, results)
    if "tv3d_beta" not in skip:
        lines += tv3d_beta(args, results)
    if "visibility" not in skip:
        lines += visibility(args, results)
    if "memory" not in skip:
        print("[memory]", flush=True)
        rows = measure_memory("sineball", sizes[0], steps=0)
        lines += ["", f"## Peak memory, STFM fast, sineball {sizes[0]}x{sizes[0]}, a whole fit to its own stop", "",
                  ("Peak RSS (VmHWM) of a fresh subprocess per frame count; 'fit adds' is the peak minus "
                  "the peak before the STFM was built (interpreter, torch, problem)."), "",
                  "| frames K | steps | refined | RSS before MiB | peak MiB | fit adds MiB |", "|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['frames']} | {r['steps']} | {'yes' if r['refined'] else 'no'} | {r['before_mib']:.0f} | "
                         f"{r['peak_mib']:.0f} | {r['peak_mib'] - r['before_mib']:.0f} |")
        lines.append(f"\nRatio of peaks at 2K vs K: {rows[1]['peak_mib'] / rows[0]['peak_mib']:.3f}; "
                     f"of what the fit adds: {(rows[1]['peak_mib'] - rows[1]['before_mib']) / max(rows[0]['peak_mib'] - rows[0]['before_mib'], 1e-9):.3f}")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
