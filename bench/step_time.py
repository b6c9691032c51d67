"""What one STFM step costs on a device: the default command's time per step, and where it goes.

    python -m bench.step_time sineball-64.h5 smoke-64.h5 --device cuda --iters 30,130
    python -m bench.step_time sineball-64.h5 --device cuda --profile prof.txt

Each bundle is reconstructed twice with `rngcam.reconstruct` (the default STFM, `max_iters` the two
counts of --iters); the difference of their solve times over the difference of their steps is the
time of a step (solve time: set-up excluded; a warm-up run first). Prints one JSON line per bundle.
`--profile`: torch.profiler over a run of the larger count, the operators' table by self time on the
host and on the device, and the count of host waits (synchronisations, copies to the host) per step.
To time another checkout's code on the same machine in the same call, put it first on PYTHONPATH and
keep the working directory off the import path (`python -m` puts it first): PYTHONSAFEPATH=1
PYTHONPATH=OTHER:. python -m bench.step_time ... (the JSON's "code" says which package ran).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def step_seconds(bundle: str, device: str, counts: tuple[int, int]) -> dict:
    """{"bundle", "device", "step_ms", "steps", "setup_s"}: a step's time from two runs."""
    import rngcam
    from rngcam import reconstruct

    solve = {}
    reconstruct(bundle, "stfm", progress=False, device=device, max_iters=2)  # warm-up: imports, kernels
    for n in counts:
        m = reconstruct(bundle, "stfm", progress=False, device=device, max_iters=n).metrics
        solve[n] = (m["seconds"] - m["setup_seconds"], m["iterations"], m["setup_seconds"])
    (s0, i0, _), (s1, i1, setup) = solve[counts[0]], solve[counts[1]]
    return {"bundle": Path(bundle).name, "device": device, "code": str(Path(rngcam.__file__).parent),
            "step_ms": 1000 * (s1 - s0) / max(i1 - i0, 1), "steps": [i0, i1], "setup_s": setup}


def profile(bundle: str, device: str, iters: int, out: Path) -> None:
    """torch.profiler's tables for a run of `iters` steps, written to `out`."""
    import torch

    from rngcam import reconstruct

    acts = [torch.profiler.ProfilerActivity.CPU]
    if device.startswith("cuda"):
        acts.append(torch.profiler.ProfilerActivity.CUDA)
    reconstruct(bundle, "stfm", progress=False, device=device, max_iters=5)  # warm-up
    t0 = time.perf_counter()
    with torch.profiler.profile(activities=acts) as prof:
        reconstruct(bundle, "stfm", progress=False, device=device, max_iters=iters)
    wall = time.perf_counter() - t0
    ka = prof.key_averages()
    waits = {e.key: e.count for e in ka if any(w in e.key for w in ("Synchronize", "Memcpy", "LaunchKernel", "item"))}
    sort_dev = "self_cuda_time_total" if len(acts) > 1 else "self_cpu_time_total"
    text = [f"{bundle}: {iters} steps, {wall:.1f} s under the profiler (set-up included); calls per step:",
            json.dumps({k: round(v / iters, 1) for k, v in sorted(waits.items())}),
            f"operators per step: {sum(e.count for e in ka) / iters:.0f}", "",
            ka.table(sort_by="self_cpu_time_total", row_limit=30), "", ka.table(sort_by=sort_dev, row_limit=30)]
    out.write_text("\n".join(text) + "\n")
    print("\n".join(text[:3]), flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bundles", nargs="+", help="bundles to reconstruct")
    p.add_argument("--device", default="cpu", help="cpu or cuda [cpu]")
    p.add_argument("--iters", default="30,130", help="the two step counts, comma-separated [30,130]")
    p.add_argument("--profile", type=Path, default=None, help="write torch.profiler's tables here instead")
    a = p.parse_args(argv)
    counts = tuple(int(x) for x in a.iters.split(","))
    if len(counts) != 2 or counts[0] >= counts[1]:
        p.error("--iters takes two increasing counts")
    if a.profile is not None:
        profile(a.bundles[0], a.device, counts[1], a.profile)
        return 0
    for b in a.bundles:
        print(json.dumps(step_seconds(b, a.device, counts)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
