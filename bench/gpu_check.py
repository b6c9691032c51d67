"""The GPU check in one call: device tests, a step's operations and time, the default at 64 px, the paper
grid and 8x, one table.

    python -m bench.gpu_check -o OUT                 # on a lent GPU (about 8 minutes)
    python -m bench.gpu_check -o OUT --device cpu --quick   # its CPU half: tiny sizes, a few steps
    python -m bench.gpu_check -o OUT --sweep chunks --skip-tests   # the paper grid's frames a graph

Each reconstruction runs rngcam.reconstruct in a child process of its own (`run` below), so the peak
GPU memory it reports is that run's alone. Every step has its own time limit; a step that fails
or runs out is a row that says so, and the rest still run. Writes OUT/gpu_check.json (with each run's
steps by level and the line it stopped on) and OUT/gpu_check.md (the table) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.program import RNGCAM

# (label, scene, size, rngcam.reconstruct's settings, child's time limit in s): the list of runs.
FULL = [
    # the default to its own stop (the budget is a backstop): issue 40's "own stop in <= 60 s"
    ("sineball 64 default", "sineball", "64", {"time_budget_s": 150}, 190),
    # the same on two of that machine's CPU threads: the GPU's ratio from one machine and one call
    ("sineball 64 default, 2 CPU threads", "sineball", "64", {"time_budget_s": 150, "device": "cpu", "threads": 2}, 190),
    ("smoke 64 default", "smoke", "64", {"time_budget_s": 150}, 190),
    ("clip 64 default", "clip", "64", {"time_budget_s": 150}, 190),
    # issue 40's GPU target: the paper grid within 0.5 dB of its converged figure in <= 60 s
    ("smoke 228x342 budget 60", "smoke", "228x342", {"time_budget_s": 60}, 150),
    ("smoke 228x342 budget 120", "smoke", "228x342", {"time_budget_s": 120}, 180),
    # where the paper grid's set-up goes on that machine (25.5 s of a 60 s budget in the fifth session)
    ("smoke 228x342 set-up profile", "smoke", "228x342", {"max_iters": 1, "profile": True}, 150),
    # at 8x the final truth evaluation (SSIM of 429 M elements) runs past the budget: give it room
    ("smoke 456x684 budget 150", "smoke", "456x684", {"time_budget_s": 150}, 300),
]
# Rows per step on the GPU, where the second session guessed a step's cost hardly grows with its rows (at the
# paper grid it does: bench/large_grids.md, "The third GPU session"): the paper grid with a 70 s budget at the
# default's 8 rows a step and at more, then the 64 px default.
ROWS_SWEEP = [
    *[(f"smoke 228x342 rows {n} budget 70", "smoke", "228x342", {"time_budget_s": 70, "rows_per_step": n}, 130)
      for n in (8, 32, 96)],
    ("sineball 64 default", "sineball", "64", {"time_budget_s": 150}, 190),
]
# Frames per autograd graph on the GPU (the CPU's 65,536-point chunk is 4 frames at the paper grid, and a
# step whose rows touch more frames than a chunk evaluates them twice): the paper grid, 70 s each.
CHUNK_SWEEP = [
    *[(f"smoke 228x342 chunk {c} rows {n} budget 70", "smoke", "228x342",
       {"time_budget_s": 70, "rows_per_step": n, "frame_chunk": c}, 130) for c, n in ((32, 8), (128, 8), (128, 32))],
]
SWEEPS = {"rows": ROWS_SWEEP, "chunks": CHUNK_SWEEP}
QUICK = [
    ("sineball 32 quick", "sineball", "32", {"max_iters": 10}, 120),
    ("smoke 32 quick", "smoke", "32", {"max_iters": 10}, 120),
]
KEYS = ("device", "wall_s", "setup_s", "iterations", "psnr_db", "psnr_intermediate_db",
        "centroid_error_median_px", "centroid_error_p90_px", "peak_gpu_gib", "peak_rss_gib", "status", "ended_by")


def child(bundle: str, out: str, device: str, settings: str) -> None:
    """Reconstruct with STFM in this process (`settings`: JSON of rngcam.reconstruct's keywords) and
    print one JSON line of its figures."""
    import torch

    from rngcam import reconstruct

    t0 = time.perf_counter()
    kwargs = {"device": device, **json.loads(settings)}  # a run's own device (a CPU baseline) wins
    profile = kwargs.pop("profile", False)
    profiler = None
    if profile:
        import cProfile

        profiler = cProfile.Profile()
        profiler.enable()
    reconstruct(bundle, "stfm", out=out, overwrite=True, progress=False, **kwargs)
    wall = time.perf_counter() - t0
    m = json.loads((Path(out) / "metrics.json").read_text())
    row = {k: m.get(k) for k in KEYS}
    row.update(wall_s=wall, setup_s=m.get("setup_seconds"), peak_rss_gib=(m.get("peak_rss_bytes") or 0) / 2**30,
               peak_gpu_gib=(torch.cuda.max_memory_allocated() / 2**30)
               if torch.cuda.is_available() and kwargs["device"] != "cpu" else None,
               psnr_60s_db=_psnr_by(Path(out) / "errors.csv", 60.0),
               level_steps=[lv.get("steps") for lv in (m.get("method_results") or {}).get("levels") or []],
               stop=(m.get("events") or [""])[-1][:300])
    if profiler is not None:
        profiler.disable()
        row["profile_top"] = _top_functions(profiler, 40)
    print("ROW " + json.dumps(row), flush=True)


def _top_functions(profiler, n: int) -> list[str]:
    """The profile's `n` rngcam functions of most cumulative time, as 'seconds calls file:line(name)'."""
    import pstats

    stats = pstats.Stats(profiler).stats
    rows = sorted(((ct, nc, f"{Path(f).name}:{line}({name})") for (f, line, name), (_cc, nc, _tt, ct, _callers)
                   in stats.items() if "rngcam" in f), reverse=True)
    return [f"{ct:8.2f} {nc:6d} {where}" for ct, nc, where in rows[:n]]


def _psnr_by(errors_csv: Path, wall_s: float) -> float | None:
    """The PSNR of the run's last log row at or before `wall_s` of its wall time (errors.csv)."""
    import csv

    if not errors_csv.exists():
        return None
    rows = [r for r in csv.DictReader(errors_csv.open()) if r.get("psnr_db") and float(r["wall_s"]) <= wall_s]
    return float(rows[-1]["psnr_db"]) if rows else None


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _sh(cmd: list[str], limit: float, log: Path) -> tuple[int, str]:
    """Run `cmd` with a time limit, its output appended to `log`; (exit code, output)."""
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=limit)
        text, rc = done.stdout + done.stderr, done.returncode
    except subprocess.TimeoutExpired as exc:
        text, rc = f"{exc.stdout or ''}{exc.stderr or ''}\n(timed out after {limit:.0f} s)", 124
    with open(log, "a") as f:
        f.write(f"$ {' '.join(cmd)}\n{text}\n")
    return rc, text


def simulate_all(out: Path, runs: list[tuple], limit: float) -> None:
    """Simulate every run's bundle at once, in parallel children (the CPUs are otherwise idle)."""
    procs = []
    for scene, size in dict.fromkeys((scene, size) for _label, scene, size, _extra, _limit in runs):
        bundle = out / f"{scene}-{size}.h5"  # once each: two runs of one bundle raced to write it
        if not bundle.exists():
            cmd = [*RNGCAM, "simulate", scene, "--size", size,
                   "-o", str(bundle)]
            procs.append((cmd, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)))
    t0 = time.perf_counter()
    with open(out / "gpu_check.log", "a") as log:
        for cmd, proc in procs:
            try:
                text = proc.communicate(timeout=max(1.0, limit - (time.perf_counter() - t0)))[0]
            except subprocess.TimeoutExpired:
                proc.kill()
                text = proc.communicate()[0] + "\n(timed out)"
            log.write(f"$ {' '.join(cmd)}\n{text}\n")
    print(f"simulated {len(procs)} bundles in {time.perf_counter() - t0:.0f} s", flush=True)


def device_tests(out: Path, limit: float) -> dict:
    """The device-parametrised tests (operators' adjoints on every device torch has)."""
    t0 = time.perf_counter()
    rc, text = _sh([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_operators.py"],
                   limit, out / "gpu_check.log")
    last = [ln for ln in text.splitlines() if ln.strip()][-1:] or ["(no output)"]
    return {"label": "device tests (tests/test_operators.py)", "status": "ok" if rc == 0 else f"exit {rc}",
            "wall_s": time.perf_counter() - t0, "summary": last[0]}


def step_figures(out: Path, runs: list[tuple], limit: float, device: str, steps: int = 10) -> dict:
    """Operations and milliseconds a step of the default fit on `device` (bench/ops_per_step.py, one CPU
    thread), per coarse-to-fine level, on the smallest grid's bundles of `runs`: the issue's "a 64 px
    step <= 5 ms" and "<= 1,500 operations" in one row."""
    size = min((r[2] for r in runs), key=lambda s: int(s.split("x")[0]))
    bundles = [str(out / f"{scene}-{size}.h5") for scene in dict.fromkeys(r[1] for r in runs if r[2] == size)]
    bundles = [b for b in bundles if Path(b).exists()]
    row = {"label": f"{size} px step (ops, ms)", "load_before": _load()}
    if not bundles:
        return {**row, "status": "no bundle (simulate failed: see gpu_check.log)"}
    t0 = time.perf_counter()
    rc, text = _sh([sys.executable, "-m", "bench.ops_per_step", *bundles, "--device", device, "--steps", str(steps),
                    "--json", str(out / "ops_per_step.json")], limit, out / "gpu_check.log")
    found = out / "ops_per_step.json"
    if rc != 0 or not found.exists():
        return {**row, "status": f"ops_per_step failed ({rc})", "wall_s": time.perf_counter() - t0}
    levels = json.loads(found.read_text())["rows"]
    summary = "; ".join(f"{r['bundle']} {r['level']}: {r['ops']:,.0f} ops, {r['ms']:.1f} ms" for r in levels)
    return {**row, "status": "ok", "summary": summary, "wall_s": time.perf_counter() - t0, "device": device,
            "steps_levels": levels}


def reconstruction(out: Path, label: str, scene: str, size: str, settings: dict, limit: float,
                   device: str) -> dict:
    """Simulate the scene and reconstruct it in a child; the row of figures."""
    stem = out / f"{scene}-{size}"
    bundle = stem.with_suffix(".h5")
    row = {"label": label, "load_before": _load()}
    if not bundle.exists():
        return {**row, "status": "no bundle (simulate failed: see gpu_check.log)"}
    rc, text = _sh([sys.executable, "-m", "bench.gpu_check", "child", str(bundle), str(stem) + "-recon",
                    device, json.dumps(settings)], limit, out / "gpu_check.log")
    rows = [ln[4:] for ln in text.splitlines() if ln.startswith("ROW ")]
    if not rows:
        return {**row, "status": f"recon failed ({rc})", "detail": text.strip().splitlines()[-3:]}
    return {**row, **json.loads(rows[-1]), "load_after": _load()}


def table(rows: list[dict], device: str) -> str:
    """The rows as one markdown table."""
    head = ["run", "device", "wall s", "set-up s", "steps", "PSNR dB", "dB by 60 s", "interm. dB", "ball px (med/p90)",
            "GPU GiB", "RSS GiB", "status", "load"]
    lines = [f"Device: {device}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def f(x, fmt="{:.1f}"):
        return "" if x is None else fmt.format(x)

    for r in rows:
        ball = "" if r.get("centroid_error_median_px") is None else \
            f"{r['centroid_error_median_px']:.2f} / {r['centroid_error_p90_px']:.2f}"
        status = r.get("status", "") + (f" ({r['ended_by']})" if r.get("ended_by") else "")
        if r.get("summary"):
            status += f": {r['summary']}"
        lines.append("| " + " | ".join([r["label"], str(r.get("device") or ""), f(r.get("wall_s")),
                                         f(r.get("setup_s")), _steps(r),
                                         f(r.get("psnr_db"), "{:.2f}"), f(r.get("psnr_60s_db"), "{:.2f}"),
                                         f(r.get("psnr_intermediate_db"), "{:.2f}"),
                                         ball, f(r.get("peak_gpu_gib"), "{:.2f}"), f(r.get("peak_rss_gib"), "{:.2f}"),
                                         status, r.get("load_before", "")]) + " |")
    return "\n".join(lines) + "\n"


def _steps(row: dict) -> str:
    """The run's steps, split by coarse-to-fine level where it had levels."""
    levels = row.get("level_steps") or []
    split = f" ({' + '.join(str(n) for n in levels)})" if len(levels) > 1 else ""
    return f"{row.get('iterations') or ''}{split}"


def _keeps(word: str, label: str, runs: list[tuple]) -> bool:
    """Whether --only's `word` keeps the row `label`: the row of that whole label where there is one,
    else every row whose label starts with it."""
    if any(r[0] == word for r in runs):
        return label == word
    return label.startswith(word)


def describe_device(device: str) -> str:
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        return f"{p.name}, {p.total_memory / 2**30:.0f} GiB, torch {torch.__version__}"
    return f"CPU, {os.cpu_count()} cores, torch {torch.__version__}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["child"]:
        child(*argv[1:5])
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--out", type=Path, required=True, help="folder for bundles, runs, the log and the table")
    p.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    p.add_argument("--quick", action="store_true", help="tiny sizes and a few steps (the CPU half, for CI)")
    p.add_argument("--skip-tests", action="store_true", help="leave out the device-parametrised tests")
    p.add_argument("--skip-step", action="store_true", help="leave out the row of a step's operations and time")
    p.add_argument("--sweep", choices=sorted(SWEEPS), help="instead of the check: the paper grid at 8, 32 and 96 rows a "
                   "step (rows) or at 32 and 128 frames per autograd graph (chunks), 70 s each")
    p.add_argument("--only", default="", help="comma-separated labels to keep, each a whole label or a prefix "
                   "(e.g. 'sineball 64 default,smoke 64': a whole label keeps that row alone; 'smoke' keeps every "
                   "smoke row, the 8x one too)")
    p.add_argument("--threads", type=int, help="CPU threads for every run that does not set its own (a CPU "
                   "baseline: --device cpu --threads 2)")
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    runs = QUICK if a.quick else SWEEPS[a.sweep] if a.sweep else FULL
    if a.only:
        runs = [r for r in runs if any(_keeps(w.strip(), r[0], runs) for w in a.only.split(",") if w.strip())]
    if a.threads:
        runs = [(label, scene, size, {"threads": a.threads, **settings}, limit)
                for label, scene, size, settings, limit in runs]
    device = describe_device(a.device)
    print(f"gpu check: {device}; {len(runs)} runs", flush=True)
    simulate_all(a.out, runs, 240)
    rows = [] if a.skip_tests else [device_tests(a.out, 120)]
    if not a.skip_step and runs:
        rows.append(step_figures(a.out, runs, 300, a.device, steps=2 if a.quick else 10))
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "steps_levels"}), flush=True)
    for label, scene, size, settings, limit in runs:
        rows.append(reconstruction(a.out, label, scene, size, settings, limit, a.device))
        print(json.dumps(rows[-1]), flush=True)
        (a.out / "gpu_check.json").write_text(json.dumps({"device": device, "rows": rows}, indent=1))
    text = table(rows, device)
    (a.out / "gpu_check.md").write_text(text)
    (a.out / "gpu_check.json").write_text(json.dumps({"device": device, "rows": rows}, indent=1))
    print(text)
    return 0 if all(str(r.get("status", "")).startswith("ok") for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
