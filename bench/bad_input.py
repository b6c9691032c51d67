"""Re-measure issue 20's table: bundles edited by hand from a 32 px simulated one, through
`rngcam inspect` and `rngcam recon` (each method under one time budget).

    flock /tmp/rngcam-bench.lock python -m bench.bad_input OUT_DIR --rows clean,saturated_gs \
        --methods tv3d,stfm,interp --budget 30

Prints one markdown row per (input, method) and writes OUT_DIR/ROW.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import time
from pathlib import Path

from bench.program import RNGCAM
from rngcam.evaluate import stress_cases as edits

ROWS = {
    "clean": [],
    "bit_depth": [edits.scale_values(16)],
    "saturated_gs": [edits.saturate_gs_frame(1)],
    "dead_rs": [edits.edit_frames("rs", lambda x: x * 0)],
    "line_time_1ns": [edits.set_attr("rs", "line_time_s", 1e-9)],
    "gs_before": [edits.set_gs_triggers(lambda t, end: edits.set_at(t, 0, -end))],
    "gs_after": [edits.set_gs_triggers(lambda t, end: edits.set_at(t, len(t) - 1, 2 * end))],
    "rs_patch_4pct": [edits.saturate_rs_patch(0.04)],
}


def rngcam(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*RNGCAM, *args], capture_output=True, text=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--methods", default="tv3d,stfm,interp")
    ap.add_argument("--budget", default="30")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    clean = a.out / "clean.h5"
    if not clean.exists():
        r = rngcam("simulate", "sineball", "-o", str(clean), "--size", "32", "--seed", "0")
        assert r.returncode == 0, r.stderr
    print(f"load {os.getloadavg()}")
    for row in a.rows.split(","):
        path = a.out / f"{row}.h5"
        if row != "clean":
            shutil.copy(clean, path)
            for hook in ROWS[row]:
                hook(path)
        ins = rngcam("inspect", str(path))
        problems = [line.split("problem", 1)[1].strip() for line in ins.stdout.splitlines()
                    if line.startswith("problem")]
        inspect = f"exit {ins.returncode}" + (f": {ins.stderr.strip()}" if ins.returncode else "")
        results = {"inspect": inspect, "problems": problems, "recon": {}}
        for method in a.methods.split(","):
            out = a.out / f"{row}-{method}"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            r = rngcam("recon", str(path), "--method", method, "-o", str(out), "--quiet",
                       "--time-budget", a.budget)
            entry = {"exit": r.returncode, "wall_s": time.perf_counter() - t0,
                     "first_lines": r.stdout.splitlines()[:6], "stderr": r.stderr.strip().splitlines()[-1:],
                     "traceback": "Traceback" in r.stderr, "folder_left": out.exists()}
            if r.returncode == 0:
                import h5py
                m = json.loads((out / "metrics.json").read_text())
                with h5py.File(out / "recon.h5") as f:
                    entry["out_max"] = float(f["video"][()].max())
                entry.update({k: m.get(k) for k in ("psnr_db", "seconds", "error_visibility",
                                                     "error_visibility_caveats", "left_out", "warnings",
                                                     "masked_fraction")})
            results["recon"][method] = entry
            psnr = f"{entry['psnr_db']:.2f} dB, max {entry['out_max']:.2f}" if "psnr_db" in entry else \
                f"exit {entry['exit']}: {' '.join(entry['stderr'])[:160]}"
            print(f"| {row} | {inspect[:60]} | {method} | {psnr} |", flush=True)
        (a.out / f"{row}.json").write_text(json.dumps(results, indent=2))
    print(f"load {os.getloadavg()}")


if __name__ == "__main__":
    main()
