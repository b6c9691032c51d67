"""Does `rngcam recon BUNDLE` (no options) give the same answer on a loaded machine as on a quiet one?

    flock /tmp/rngcam-bench.lock .venv/bin/python -m bench.default_under_load --hogs 2 \
        --out bench/default_under_load.json BUNDLE...

Each bundle is reconstructed twice by a fresh `rngcam recon BUNDLE -o DIR --quiet` process, the
command a user types: once with nothing else running, once beside `--hogs` busy-looping processes
(one per core saturates this 2-core machine). The table gives wall time, status, iterations,
intermediate-frame PSNR, moving-region PSNR and, on a one-object scene, the ball's centroid error,
with the load average at the start of each run. Run it on a quiet machine: the "quiet" rows are
only quiet if nothing else is.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.program import RNGCAM

CLI = RNGCAM
KEYS = ("status", "threads", "iterations", "psnr_intermediate_db", "psnr_dynamic_db", "centroid_error_median_px",
        "centroid_error_p90_px", "ghost_median")


def _spin() -> None:
    while True:
        pass


def one_run(bundle: Path, out: Path, hogs: int) -> dict:
    """`rngcam recon bundle` beside `hogs` busy processes; its figures, wall time and load."""
    spinners = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(hogs)]
    for s in spinners:
        s.start()
    try:
        time.sleep(5 if hogs else 0)  # let the load average see them
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        done = subprocess.run([*CLI, "recon", str(bundle), "-o", str(out), "--quiet"], capture_output=True, text=True)
        wall = time.perf_counter() - t0
    finally:
        for s in spinners:
            s.terminate()
    row = {"bundle": bundle.name, "hogs": hogs, "load_start": round(load, 2), "wall_s": round(wall, 1),
           "exit": done.returncode, "last_line": (done.stdout.strip().splitlines() or [""])[-1]}
    metrics = out / "metrics.json"
    if metrics.exists():
        m = json.loads(metrics.read_text())
        row.update({k: m[k] for k in KEYS if k in m})
        row["notes"] = [n for n in m.get("notes", []) if "preset" in n or "floor" in n or "GS-only" in n][:3]
        row["events"] = m.get("events", [])[-2:]
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundles", nargs="+", type=Path)
    ap.add_argument("--hogs", type=int, default=2, help="busy processes beside the loaded run")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the rows")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for bundle in args.bundles:
            for hogs in (0, args.hogs):
                row = one_run(bundle, Path(tmp) / f"{bundle.stem}-{hogs}", hogs)
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=1))
    print("\n| bundle | hogs | load | wall s | status | iterations | interm. dB | moving dB | centroid px |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ball = (f"{r['centroid_error_median_px']:.2f} / {r['centroid_error_p90_px']:.2f}"
                if "centroid_error_median_px" in r else "-")
        print(f"| {r['bundle']} | {r['hogs']} | {r['load_start']:.2f} | {r['wall_s']:.1f} | {r.get('status')} | "
              f"{r.get('iterations')} | {r.get('psnr_intermediate_db', float('nan')):.2f} | "
              f"{r.get('psnr_dynamic_db', float('nan')):.2f} | {ball} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
