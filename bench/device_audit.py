"""Every method and preset for a few steps on a device, in one process: which ones run there.

    python -m bench.device_audit --device cuda -o OUT

A tensor left on the host while the problem sits on the GPU fails only on a GPU; this runs each
method through rngcam.reconstruct (and STFM's presets, a held-out split, a coarse-to-fine grid and
a resume) for a few steps and prints one line per case: ok, or the error and the rngcam line it came from.
"""

from __future__ import annotations

import argparse
import time
import traceback
from pathlib import Path

CASES = [  # (label, scene, size, method label, rngcam.reconstruct's settings)
    ("stfm auto", "sineball", 32, "stfm", {"max_iters": 5}),
    ("stfm fast", "sineball", 32, "stfm-fast", {"max_iters": 5}),
    ("stfm prior", "sineball", 32, "stfm-prior", {"max_iters": 5}),
    ("stfm paper", "sineball", 32, "stfm-paper", {"max_iters": 5}),
    ("stfm holdout", "sineball", 32, "stfm", {"holdout": 0.1, "max_iters": 5}),
    ("stfm resume", "sineball", 32, "stfm", {"max_iters": 8, "resume": True}),
    ("stfm 96 coarse-to-fine", "smoke", 96, "stfm", {"time_budget_s": 25}),
    ("tv3d", "sineball", 32, "tv3d", {"max_iters": 5}),
    ("pnp", "sineball", 32, "pnp", {"max_iters": 3}),
    ("blend", "sineball", 32, "blend", {}),
    ("interp", "sineball", 32, "interp", {}),
    ("rife", "sineball", 32, "rife", {}),
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
    from rngcam import reconstruct
    from rngcam.errors import RngcamError
    from rngcam.sim.simulate import simulate

    a.out.mkdir(parents=True, exist_ok=True)
    failed = 0
    for label, scene, size, method, settings in CASES:
        bundle = a.out / f"audit-{scene}-{size}.h5"
        out = a.out / ("audit-" + label.replace(" ", "-"))
        t0 = time.perf_counter()
        try:
            if not bundle.exists():
                simulate(scene, bundle, size=size)
            if settings.get("resume"):  # a checkpoint to resume from: a short run first
                reconstruct(bundle, method, out=out, progress=False, device=a.device, overwrite=True, max_iters=4)
            result = reconstruct(bundle, method, out=out, progress=False, device=a.device,
                                 overwrite=not settings.get("resume"), **settings)
            if result.status == "failed":
                failed += 1
                print(f"AUDIT FAILED {label}: {result.message}", flush=True)
            else:
                print(f"AUDIT ok     {label} ({result.status}, {time.perf_counter() - t0:.1f} s)", flush=True)
        except RngcamError as exc:
            failed += 1
            print(f"AUDIT error  {label}: {exc}", flush=True)
        except Exception as exc:  # noqa: BLE001 - each case is one line
            failed += 1
            print(f"AUDIT FAILED {label}: {type(exc).__name__}: {str(exc)[:160]} at {where(exc)}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
