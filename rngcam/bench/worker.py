"""One benchmark run in a fresh process: `python -m rngcam.bench.worker JOB.json`.

The job names the bundle, the output folder, the runner method, its options, the time budget
and the log spacing. It calls `rngcam.recon.runner.reconstruct` (which writes every output)
and adds `bench_worker.json` with this process's peak resident set size and its base (the
resident size once the interpreter, torch and the output writers are loaded, before the run):
peak - base is what the method itself added.

Peak memory is read from /proc/self/status (VmHWM: the high-water mark of this process's own
address space, which starts afresh at exec). `ru_maxrss` is not used for this: Linux carries
the parent's peak over fork and exec into it, so a child of a large process reports at least
the parent's size.
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path


def _status_kib(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def peak_rss_bytes() -> int:
    """This process's peak resident set size (VmHWM), or ru_maxrss where /proc is missing."""
    kib = _status_kib("VmHWM")
    return kib * 1024 if kib is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def current_rss_bytes() -> int:
    """This process's resident set size now (VmRSS; 0 where /proc is missing)."""
    return (_status_kib("VmRSS") or 0) * 1024


def _import_output_writers() -> None:
    """Load what writing the outputs loads, so the base figure holds every library."""
    import av  # noqa: F401
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot
    import tifffile  # noqa: F401


def main(job_path: str) -> int:
    job = json.loads(Path(job_path).read_text())
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    report = {"error": ""}
    try:
        import cv2
        import torch

        from rngcam.recon.runner import ReconSettings, reconstruct

        torch.set_num_threads(int(job.get("threads", 1)))
        cv2.setNumThreads(int(job.get("threads", 1)))
        _import_output_writers()
        report["base_rss_bytes"] = current_rss_bytes()

        settings = ReconSettings(method=job["method"], time_budget_s=job["time_budget_s"], progress=False,
                                 log_every_s=job["log_every_s"], checkpoint_every_s=1e9,
                                 options=job.get("options", {}))
        reconstruct(job["bundle"], out, settings, echo=lambda _msg: None)
    except Exception as exc:  # noqa: BLE001 - reported in the results table, not raised
        report["error"] = f"{type(exc).__name__}: {exc}"
    report["peak_rss_bytes"] = peak_rss_bytes()
    (out / "bench_worker.json").write_text(json.dumps(report))
    return 1 if report["error"] else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
