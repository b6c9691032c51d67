"""Does `rngcam recon --time-budget B` end near B with every method? Wall time of each, by hand:

    flock /tmp/rngcam-bench.lock .venv/bin/python -m bench.recon_budget --budget 20 --out bench/recon_budget.md

Each method runs as a user runs it (a fresh `rngcam recon` process, interpreter start included) on
the demo's bundle (a mock-rig capture, rigs/mock.yaml); the table gives the wall time against
the target (budget x 1.1 + 5 s), the status, iterations, the set-up's seconds and the load average
before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

from bench.program import RNGCAM
from rngcam.recon import registry

ROOT = Path(__file__).resolve().parents[1]
CLI = RNGCAM


def load() -> str:
    return f"{os.getloadavg()[0]:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--budget", type=float, default=20.0)
    ap.add_argument("--methods", default=",".join(registry.names()))
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    target = 1.1 * a.budget + 5
    lines = [f"# `rngcam recon --time-budget {a.budget:g}` on the demo's bundle: wall time per method", "",
             f"`python -m bench.recon_budget --budget {a.budget:g}`; target: wall <= {target:g} s.", "",
             "| method | wall s | status | iterations | set-up s | load before / after |", "|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        bundle = Path(tmp) / "mock.h5"
        subprocess.run([*CLI, "capture", "--rig", str(ROOT / "rigs" / "mock.yaml"), "-o", str(bundle)], check=True,
                       capture_output=True)
        for method in a.methods.split(","):
            out = Path(tmp) / method
            before, t0 = load(), time.perf_counter()
            proc = subprocess.run([*CLI, "recon", str(bundle), "--method", method, "--time-budget", str(a.budget),
                                   "-o", str(out), "--quiet"], capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if proc.returncode:
                lines.append(f"| {method} | {wall:.1f} | exit {proc.returncode}: {proc.stderr.strip()[-120:]} | | | |")
                continue
            m = json.loads((out / "metrics.json").read_text())
            lines.append(f"| {method} | {wall:.1f}{'' if wall <= target else ' (over)'} | {m['status']} | "
                         f"{m['iterations']} | {m['setup_seconds']:.1f} | {before} / {load()} |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        a.out.write_text(text)


if __name__ == "__main__":
    main()
