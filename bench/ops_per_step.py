"""How many torch operations one STFM step runs, and its time at one thread, for the default fit at 64 px.

    python -m bench.ops_per_step                      # smoke and sineball, simulated at 64 px
    python -m bench.ops_per_step shot.h5 --steps 20   # bundles of your own
    python -m bench.ops_per_step --device cuda --json ops.json   # on a GPU (bench/gpu_check.py runs it)

Each bundle's default STFM (`preset auto`) is built as `rngcam recon` builds it (`make_stfm` on the
problem the runner reads) and stepped: first its coarse level (the half grid, an ensemble of fits: one
of them stepped a call at one thread), then, after `_next_level`, its full level at 64 px (one fit
on the coarse level's video). Per level: a few warm-up steps, then `--steps` steps under
torch.profiler, whose recorded aten operator events (views included, `aten::` in the name) are counted
per step; then `--steps` steps timed without the profiler. One thread (torch.set_num_threads(1)).
Prints a table and the load average (timings on a shared machine vary with it); `--top N` prints each
level's N most called operators per step.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections import Counter
from pathlib import Path

SCENES = ("smoke", "sineball")


def build_default(path: Path, device: str = "cpu"):
    """The default STFM run on the bundle at `path`, as the runner makes it (float32, no truth), on `device`."""
    import torch

    from rngcam.api import open_bundle
    from rngcam.recon import registry
    from rngcam.recon.methods.stfm import make_stfm
    from rngcam.recon.problem import build_problem
    from rngcam.recon.runner import method_view

    settings = registry.get("stfm").settings()  # the command's default: preset auto
    problem = method_view(build_problem(open_bundle(path).bundle), settings).to(torch.float32)
    return make_stfm(problem, settings, device)


def count_ops(step, steps: int) -> tuple[float, Counter]:
    """(aten operator events per call of `step`, their names' counts per call) over `steps` calls."""
    import torch

    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            step()
    names = Counter(e.name for e in prof.events() if e.name.startswith("aten::"))
    return sum(names.values()) / steps, Counter({k: v / steps for k, v in names.items()})


def time_steps(step, steps: int, device: str = "cpu") -> float:
    """Milliseconds a call of `step`, over `steps` calls (on CUDA, from a synchronised start to a
    synchronised end)."""
    import torch

    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync()
    return 1000 * (time.perf_counter() - t0) / steps


def describe(method) -> str:
    """The fit a level steps: one STFM (its preset, grid) or an ensemble of them."""
    fits = getattr(method, "members", None) or [method]
    one = fits[0]
    base = one.base.source or "none"
    return (f"{len(fits)} x {one.resolved.settings.preset} {one.H}x{one.W}x{one.K} "
            f"(base {base}, motion {one.resolved.motion_model})")


def measure(path: Path, steps: int, warmup: int, top: int, device: str = "cpu") -> list[dict]:
    """One row per level of the default fit on the bundle at `path`, on `device`."""
    run = build_default(path, device)
    rows = []
    levels = getattr(run, "problems", None)
    for level in range(len(levels) if levels else 1):
        if level > 0:
            run._next_level()  # the full level, started from the coarse level's video as a run starts it
        fit = run.method if levels else run
        for _ in range(warmup):
            run.step()
        ops, names = count_ops(run.step, steps)
        ms = time_steps(run.step, steps, device)
        rows.append({"bundle": path.stem, "level": level + 1, "fit": describe(fit), "ops": ops, "ms": ms,
                     "top": names.most_common(top)})
    return rows


def main(argv: list[str] | None = None) -> int:
    import torch

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bundles", nargs="*", type=Path, help="bundles (default: smoke and sineball simulated at 64 px)")
    p.add_argument("--steps", type=int, default=10, help="steps profiled, and steps timed [10]")
    p.add_argument("--warmup", type=int, default=3, help="steps before the profiled ones, per level [3]")
    p.add_argument("--top", type=int, default=0, help="print each level's N most called operators [0]")
    p.add_argument("--device", default="cpu", help="where the fit runs: cpu (one thread) or cuda [cpu]")
    p.add_argument("--json", type=Path, default=None, help="also write the rows to this JSON file")
    a = p.parse_args(argv)
    if a.device.startswith("cuda") and not torch.cuda.is_available():
        p.error(f"--device {a.device}: torch sees no CUDA device")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        bundles = list(a.bundles)
        if not bundles:
            from rngcam.sim.simulate import simulate

            for scene in SCENES:
                bundles.append(Path(tmp) / f"{scene}.h5")
                simulate(scene, bundles[-1], size=64)
        rows = [r for b in bundles for r in measure(b, a.steps, a.warmup, a.top, a.device)]
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}, torch {torch.__version__}, "
          f"{a.device}, 1 CPU thread")
    if a.json is not None:
        a.json.write_text(json.dumps({"device": a.device, "torch": torch.__version__, "rows": rows}, indent=1))
    print(f"{'bundle':<12} {'level':>5} {'ops/step':>9} {'ms/step':>8}  fit")
    for r in rows:
        print(f"{r['bundle']:<12} {r['level']:>5} {r['ops']:>9.0f} {r['ms']:>8.1f}  {r['fit']}")
        for name, count in r["top"]:
            print(f"{'':<18}{count:>9.1f}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
