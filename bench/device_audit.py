"""Every method and preset for a few steps on a device, in one process: which ones run there.

    python -m bench.device_audit --device cuda -o OUT

A tensor left on the host while the problem sits on the GPU fails only on a GPU; this runs each
method (and STFM's presets, a held-out split, a coarse-to-fine grid and a resume) for a few steps
and prints one line per case: ok, or the error and the rngcam line it came from.
"""

from __future__ import annotations

import argparse
import time
import traceback
from pathlib import Path

CASES = [  # (label, scene, size, recon arguments)
    ("stfm auto", "sineball", "32", ["--iters", "5"]),
    ("stfm fast", "sineball", "32", ["--preset", "fast", "--iters", "5"]),
    ("stfm prior", "sineball", "32", ["--preset", "prior", "--iters", "5"]),
    ("stfm paper", "sineball", "32", ["--preset", "paper", "--iters", "5"]),
    ("stfm holdout", "sineball", "32", ["--holdout", "0.1", "--iters", "5"]),
    ("stfm resume", "sineball", "32", ["--iters", "8", "--resume"]),
    ("stfm 96 coarse-to-fine", "smoke", "96", ["--time-budget", "25"]),
    ("tv3d", "sineball", "32", ["--method", "tv3d", "--iters", "5"]),
    ("pnp", "sineball", "32", ["--method", "pnp", "--iters", "3"]),
    ("blend", "sineball", "32", ["--method", "blend"]),
    ("interp", "sineball", "32", ["--method", "interp"]),
    ("rife", "sineball", "32", ["--method", "rife"]),
]


def where(exc: BaseException) -> str:
    """The innermost rngcam frame of `exc`'s traceback, as file:line."""
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if "/rngcam/" in f.filename]
    return f"{Path(frames[-1].filename).name}:{frames[-1].lineno} {frames[-1].line}" if frames else ""


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--out", type=Path, required=True)
    p.add_argument("--device", default="cuda")
    a = p.parse_args()
    from rngcam.cli import main as cli

    a.out.mkdir(parents=True, exist_ok=True)
    failed = 0
    for label, scene, size, extra in CASES:
        bundle = a.out / f"audit-{scene}-{size}.h5"
        t0 = time.perf_counter()
        try:
            if not bundle.exists():
                cli(["simulate", scene, "--size", size, "-o", str(bundle)], standalone_mode=False)
            out = a.out / ("audit-" + label.replace(" ", "-"))
            first = ["--overwrite"] if "--resume" not in extra else []
            if "--resume" in extra:  # a checkpoint to resume from: a short run first
                cli(["recon", str(bundle), "-o", str(out), "--overwrite", "--quiet", "--device", a.device,
                     "--iters", "4"], standalone_mode=False)
            cli(["recon", str(bundle), "-o", str(out), *first, "--quiet", "--device", a.device, *extra],
                standalone_mode=False)
            print(f"AUDIT ok     {label} ({time.perf_counter() - t0:.1f} s)", flush=True)
        except SystemExit as exc:
            failed += exc.code not in (0, None)
            print(f"AUDIT exit {exc.code} {label}", flush=True)
        except Exception as exc:  # noqa: BLE001 - each case is one line
            failed += 1
            print(f"AUDIT FAILED {label}: {type(exc).__name__}: {str(exc)[:160]} at {where(exc)}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
