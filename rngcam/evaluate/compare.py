"""`rngcam bench`: every method on every benchmark scene under the same time budget.

Each (scene, method) runs in its own process (`rngcam.evaluate.worker`, through `reconstruct`),
one after another, so each gets the whole machine and its peak memory is its own. Iterative
methods run for the time budget; GS-only baselines run once. From each run's error-vs-time
log the table reports PSNR/SSIM over all and intermediate frames, the solve time at which
the PSNR first reaches the best GS-only PSNR of the scene, and that +1 dB and +3 dB,
seconds, iterations and peak memory; and each scene gets one error-against-time plot.
"""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from rngcam.evaluate import report
from rngcam.evaluate.scenes import BenchScene, make_scene_bundle
from rngcam.recon import registry
from rngcam.recon.outputs import plot_errors

LEVEL_OFFSETS_DB = (0.0, 1.0, 3.0)  # above the best GS-only PSNR of the scene
KILL_GRACE_S = 300.0  # extra time a run may take beyond its budget before it is stopped


@dataclass(frozen=True)
class BenchSettings:
    """Image size (pixels on a side), time budget per iterative run (s), methods, seed, and
    the CPU threads each run may use. One thread by default: on a shared 2-core machine two
    OpenMP threads made runs 20-80x slower whenever another process was busy."""

    size: int = 64
    time_budget_s: float = 60.0
    methods: tuple[str, ...] = registry.bench_labels()  # registry labels, e.g. stfm-fast, tv3d, blend
    seed: int = 0
    threads: int = 1

    @classmethod
    def quick(cls, **overrides) -> BenchSettings:
        """Small scenes and short budgets: the whole benchmark in a few minutes on 2 cores."""
        return cls(**{"size": 32, "time_budget_s": 10.0, **overrides})


def unavailable(method: str) -> str:
    """Why the method of label `method` cannot run here ('' when it can)."""
    return registry.unavailable(method)


def _gs_only(method: str) -> bool:
    return not registry.parse_label(method)[0].iterative


# ----------------------------------------------------------------------------- one run


def _floats(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            out[k] = v
    return out


def read_log(path: Path) -> list[dict]:
    """errors.csv as a list of rows with numbers as floats ([] when missing)."""
    if not path.is_file():
        return []
    with open(path) as fh:
        return [_floats(r) for r in csv.DictReader(fh)]


def run_one(bundle: Path, out: Path, method: str, settings: BenchSettings) -> dict:
    """Run `method` on `bundle` in a fresh process; returns its result row and log."""
    out.mkdir(parents=True, exist_ok=True)
    job = {"bundle": str(bundle), "out": str(out), "method": method,
           "time_budget_s": settings.time_budget_s, "log_every_s": max(settings.time_budget_s / 40, 0.2),
           "threads": settings.threads}
    job_path = out / "bench_job.json"
    job_path.write_text(json.dumps(job))
    timeout = settings.time_budget_s + KILL_GRACE_S
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": str(settings.threads), "MKL_NUM_THREADS": str(settings.threads)}
    proc = subprocess.Popen([sys.executable, "-m", "rngcam.evaluate.worker", str(job_path)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        output, _ = proc.communicate(timeout=timeout)
        status = "ok" if proc.returncode == 0 else "error"
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        status = "timeout"
    process_s = time.perf_counter() - t0
    (out / "bench_worker.log").write_bytes(output or b"")
    row: dict = {"method": method, "status": status, "process_s": process_s}
    worker = out / "bench_worker.json"
    info = json.loads(worker.read_text()) if worker.is_file() else {}
    if info.get("peak_rss_bytes"):
        row["peak_rss_mb"] = info["peak_rss_bytes"] / 2**20
        if info.get("base_rss_bytes"):
            row["added_rss_mb"] = (info["peak_rss_bytes"] - info["base_rss_bytes"]) / 2**20
    message = info.get("error", "")
    if status == "timeout":
        message = f"stopped after {timeout:.0f} s"
    elif status == "error" and not message:
        tail = (output or b"").decode(errors="replace").strip().splitlines()[-1:]
        message = f"exit code {proc.returncode}: {' '.join(tail)}"
    metrics_path = out / "metrics.json"
    if metrics_path.is_file() and status != "timeout":
        m = json.loads(metrics_path.read_text())
        for key in ("psnr_db", "psnr_intermediate_db", "ssim", "ssim_intermediate", "seconds", "iterations",
                    *MOTION_COLUMNS):
            if key in m:
                row[key] = m[key]
        if m.get("status", "ok") != "ok" and status == "ok":
            row["status"] = m["status"]
    row["message"] = message
    row["log"] = read_log(out / "errors.csv")
    return row


# ----------------------------------------------------------------------------- levels and plots


def time_to_level(log: list[dict], level: float) -> float:
    """First solve_s at which psnr_db >= level (NaN if never)."""
    for r in log:
        p = r.get("psnr_db")
        if isinstance(p, float) and math.isfinite(p) and p >= level:
            return float(r["solve_s"])
    return math.nan


def level_columns(best_gs_db: float) -> dict[str, float]:
    """Column name -> PSNR level, e.g. {'t_gs_s': 19.1, 't_gs+1dB_s': 20.1, 't_gs+3dB_s': 22.1}."""
    return {("t_gs_s" if d == 0 else f"t_gs+{d:g}dB_s"): best_gs_db + d for d in LEVEL_OFFSETS_DB}


def add_level_times(rows: list[dict]) -> dict[str, float]:
    """Fill each row of one scene with its time to each level; returns the levels."""
    gs = [r["psnr_db"] for r in rows if _gs_only(r["method"]) and isinstance(r.get("psnr_db"), float)
          and math.isfinite(r["psnr_db"])]
    if not gs:
        return {}
    levels = level_columns(max(gs))
    for r in rows:
        for col, level in levels.items():
            r[col] = time_to_level(r.get("log", []), level)
    return levels


def plot_scene(png: Path, rows: list[dict], budget_s: float) -> None:
    """Every method's error against solve time on one figure; a one-shot baseline is drawn
    as a flat line from when it finished to the end of the budget."""
    runs = {}
    for r in rows:
        log = [x for x in r.get("log", []) if isinstance(x.get("solve_s"), float)]
        if not log:
            continue
        if _gs_only(r["method"]) and len(log) == 1:
            log = [log[0], {**log[0], "solve_s": max(budget_s, log[0]["solve_s"])}]
        runs[r["method"]] = log
    if runs:
        plot_errors(png, runs)


# ----------------------------------------------------------------------------- the benchmark


def run_bench(out: Path, scenes: list[BenchScene], settings: BenchSettings,
              echo=print) -> list[dict]:
    """Simulate each scene, run every method on it, write results.csv/.md and the plots."""
    out = Path(out)
    (out / "bundles").mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows: list[dict] = []
    skipped = {m: why for m in settings.methods if (why := unavailable(m))}
    methods = [m for m in settings.methods if m not in skipped]
    for m, why in skipped.items():
        echo(f"skipping {m}: {why}")
    sources = {}
    levels_by_scene = {}
    for scene in scenes:
        bundle = out / "bundles" / f"{scene.name}.h5"
        t0 = time.perf_counter()
        sources[scene.name] = make_scene_bundle(scene, bundle, settings.size, settings.seed)
        echo(f"{scene.name}: simulated in {time.perf_counter() - t0:.1f} s")
        scene_rows = []
        for method in methods:
            r = run_one(bundle, out / "runs" / scene.name / method, method, settings)
            r = {"scene": scene.name, **r}
            scene_rows.append(r)
            psnr = r.get("psnr_db")
            echo(f"  {method:10s} {r['status']:7s} PSNR {report.fmt(psnr)} dB  "
                 f"{report.fmt(r.get('seconds'))} s  {report.fmt(r.get('peak_rss_mb'))} MB"
                 + (f"  {r['message']}" if r["message"] else ""))
        levels_by_scene[scene.name] = add_level_times(scene_rows)
        plot_scene(out / f"errors_{scene.name}.png", scene_rows, settings.time_budget_s)
        rows += scene_rows
    elapsed = time.perf_counter() - t_start
    write_results(out, rows, settings, levels_by_scene, sources, skipped, elapsed)
    return rows


MOTION_COLUMNS = ("psnr_dynamic_db", "centroid_error_median_px", "centroid_error_p90_px", "ghost_median")
COLUMNS = ["scene", "method", "status", "psnr_db", "psnr_intermediate_db", *MOTION_COLUMNS, "ssim",
           "ssim_intermediate",
           "t_gs_s", "t_gs+1dB_s", "t_gs+3dB_s", "seconds", "iterations", "peak_rss_mb", "added_rss_mb",
           "process_s",
           "message"]
HEADERS = {"psnr_db": "PSNR dB", "psnr_intermediate_db": "PSNR inter.", "psnr_dynamic_db": "PSNR moving",
           "centroid_error_median_px": "centroid med px", "centroid_error_p90_px": "centroid p90 px",
           "ghost_median": "ghost", "ssim": "SSIM",
           "ssim_intermediate": "SSIM inter.", "t_gs_s": "t(GS best) s", "t_gs+1dB_s": "t(+1 dB) s",
           "t_gs+3dB_s": "t(+3 dB) s", "seconds": "solve s", "peak_rss_mb": "peak MB",
           "added_rss_mb": "added MB",
           "process_s": "process s"}


_LEVEL_NAMES = {"t_gs_s": "best GS-only", "t_gs+1dB_s": "+1 dB", "t_gs+3dB_s": "+3 dB"}


def write_results(out: Path, rows: list[dict], settings: BenchSettings, levels: dict, sources: dict,
                  skipped: dict, elapsed_s: float) -> None:
    """results.csv (one row per scene and method) and results.md (a table per scene)."""
    flat = [{k: v for k, v in r.items() if k != "log"} for r in rows]
    report.write_csv(out / "results.csv", flat, COLUMNS)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    md = ["# rngcam bench", "",
          (f"{settings.size}x{settings.size} px scenes; iterative methods get {settings.time_budget_s:g} s "
           f"each (wall clock, set-up included); GS-only baselines run once. Every run is its own "
           f"process, one at a time, with {settings.threads} CPU thread(s) on a {os.cpu_count()}-core machine "
           f"(load average {load:.1f} at the end). "
           f"Total {elapsed_s / 60:.1f} min."),
          "",
          ("Columns: PSNR/SSIM against the simulated truth over all frames and over the intermediate "
           "frames (away from the GS key frames); PSNR moving = PSNR over the intermediate frames' moving region "
           "(where the truth differs from its temporal median, grown by 2 px); on one-object scenes the "
           "object's centroid error (median, 90th percentile, px) and ghost (median share of its signal "
           "outside the true object grown by 2 px); t(...) = solve time at which the PSNR first reached the "
           "best GS-only PSNR of the scene, and that +1 dB, +3 dB ('-' = never); solve s = time spent "
           "solving (set-up included); peak MB = the run's peak resident memory (its own process, "
           "outputs written); added MB = peak minus the process's size before the run (interpreter, "
           "torch and output writers loaded); "
           "process s = the whole process (start-up and outputs included)."), ""]
    if skipped:
        md += ["Not run: " + "; ".join(f"{m} ({why})" for m, why in skipped.items()), ""]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        lv = levels.get(scene, {})
        md += [f"## {scene}", "", f"Simulated: {sources.get(scene, '?')}."]
        if lv:
            md.append("PSNR levels: " + ", ".join(f"{_LEVEL_NAMES[c]} {v:.2f} dB" for c, v in lv.items()) + ".")
        md += ["", report.markdown_table([r for r in flat if r["scene"] == scene],
                                         [c for c in COLUMNS if c != "scene"], HEADERS),
               "", f"![error against run time, {scene}](errors_{scene}.png)", ""]
    (out / "results.md").write_text("\n".join(md))
