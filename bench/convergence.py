"""How long `rngcam recon BUNDLE` (no options) takes to its own stop at 64 px, before and after a change.

    flock /tmp/rngcam-bench.lock .venv/bin/python -m bench.convergence \
        --checkout before=/path/to/older/checkout --checkout after=. --out bench/convergence.json

Each scene (sineball, smoke, the packaged clip) is simulated once with `--fidelity fine` by this
checkout, then reconstructed by a fresh `python -m rngcam recon BUNDLE -o DIR --quiet` of each
checkout (PYTHONPATH points at it), one process at a time, the command a user types. A row gives
the load average at its start, wall time of the whole command, set-up, iterations (and each
ensemble member's steps), intermediate-frame PSNR and the ball's centroid error. Run it on a quiet
machine: the rows are only comparable if nothing else runs. `--report` prints the table of `--out`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("sineball", "smoke", "clip")


def simulate(scene: str, folder: Path, size: int) -> Path:
    out = folder / f"{scene}-fine.h5"
    subprocess.run([sys.executable, "-m", "rngcam", "simulate", scene, "-o", str(out), "--size", str(size),
                    "--fidelity", "fine", "--overwrite"], check=True, capture_output=True, cwd=ROOT)
    return out


def recon(bundle: Path, checkout: Path, out: Path) -> dict:
    """One `rngcam recon` of `checkout` on `bundle`: its figures, wall time and the load at its start."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "rngcam", "recon", str(bundle), "-o", str(out), "--quiet",
                           "--overwrite"], capture_output=True, text=True, env=env, cwd=out.parent)
    row = {"load_start": round(load, 2), "wall_s": round(time.perf_counter() - t0, 1), "exit": done.returncode}
    if done.returncode:
        row["error"] = (done.stdout + done.stderr).strip().splitlines()[-1:]
        return row
    m = json.loads((out / "metrics.json").read_text())
    results = m.get("method_results", {})
    row.update({"setup_s": round(m["setup_seconds"], 1), "solve_s": round(m["seconds"], 1),
                "iterations": m["iterations"], "member_steps": results.get("member_steps"),
                "refine_steps": results.get("refine_steps"), "ended_by": m["ended_by"],
                "psnr_intermediate_db": round(m["psnr_intermediate_db"], 2),
                "centroid_px": [round(m[k], 2) for k in ("centroid_error_median_px", "centroid_error_p90_px") if k in m]})
    return row


def table(rows: list[dict]) -> str:
    lines = ["| scene | checkout | load | wall s | set-up s | iterations (member steps + refinement) | "
             "intermediate dB | ball px (median / p90) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        steps = str(r.get("iterations", "-"))
        if r.get("member_steps"):
            steps += f" ({' + '.join(map(str, r['member_steps']))} + {r.get('refine_steps') or 0})"
        ball = " / ".join(f"{x:.2f}" for x in r.get("centroid_px", [])) or "-"
        lines.append(f"| {r['scene']} | {r['checkout']} | {r['load_start']:.2f} | {r['wall_s']:.1f} | "
                     f"{r.get('setup_s', '-')} | {steps} | {r.get('psnr_intermediate_db', '-')} | {ball} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkout", action="append", default=None, metavar="NAME=PATH",
                    help="a checkout to time (repeatable; default: after=this one)")
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma-separated scenes")
    ap.add_argument("--size", type=int, default=64, help="grid size N (N x N)")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the rows")
    ap.add_argument("--report", action="store_true", help="print the table of --out and stop")
    args = ap.parse_args(argv)
    if args.report:
        print(table(json.loads(args.out.read_text())))
        return 0
    checkouts = [c.split("=", 1) for c in (args.checkout or [f"after={ROOT}"])]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for scene in args.scenes.split(","):
            bundle = simulate(scene, folder, args.size)
            for name, path in checkouts:
                row = {"scene": scene, "checkout": name, **recon(bundle, Path(path).resolve(), folder / f"{scene}-{name}")}
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
