"""One benchmark run in a fresh process: `python -m rngcam.evaluate.worker JOB.json`.

The job names the bundle, the output folder, the method's registry label (e.g. stfm-fast), any
settings it overrides by name (`overrides`), the time budget and the log spacing. It calls
`rngcam.api.reconstruct` (which writes every output)
and adds `bench_worker.json` with this process's peak resident set size and its base (the
resident size once the interpreter, torch and the output writers are loaded, before the run):
peak - base is what the method itself added.

Peak memory comes from rngcam.memory (VmHWM, which starts afresh at exec; not ru_maxrss).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from rngcam.memory import current_rss_bytes, peak_rss_bytes


def _import_output_writers() -> None:
    """Load what writing the outputs loads, so the base figure holds every library."""
    import av  # noqa: F401  # heavy: av
    import matplotlib  # heavy: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # heavy: matplotlib
    import tifffile  # noqa: F401  # heavy: tifffile


def main(job_path: str) -> int:
    job = json.loads(Path(job_path).read_text())
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    report = {"error": ""}
    try:
        import cv2  # heavy: cv2
        import torch  # heavy: torch

        from rngcam.api import reconstruct  # heavy: api loads cv2, h5py, torch

        torch.set_num_threads(int(job.get("threads", 1)))
        cv2.setNumThreads(int(job.get("threads", 1)))
        _import_output_writers()
        report["base_rss_bytes"] = current_rss_bytes()
        result = reconstruct(job["bundle"], job["method"], out=out, progress=False, time_budget_s=job["time_budget_s"],
                             log_every_s=job["log_every_s"], checkpoint_every_s=1e9,
                             overwrite=True,  # the folder already holds this job's own files
                             threads=int(job.get("threads", 1)),  # the comparison's count, whatever the load
                             **job.get("overrides", {}))
        if result.status == "failed":
            report["error"] = f"RngcamError: {result.message}"
    except Exception as exc:  # noqa: BLE001 - reported in the results table, not raised
        report["error"] = f"{type(exc).__name__}: {exc}"
    report["peak_rss_bytes"] = peak_rss_bytes()
    (out / "bench_worker.json").write_text(json.dumps(report))
    return 1 if report["error"] else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
