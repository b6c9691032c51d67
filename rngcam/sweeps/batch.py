"""Reconstruct many bundles: one task per bundle, skip what is done, a summary table at the end.

Each bundle goes to <out>/<bundle stem>/ (rngcam.api.reconstruct, every usual output)
and is marked done there with its checksum and settings (batch-done.json): a re-run skips it.
A bundle that fails (bad file, failed fit, lost worker) is a row in the summary, not the end
of the batch. Summary: <out>/batch.csv and <out>/batch.md.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from rngcam.api import keywords, reconstruct
from rngcam.errors import RngcamError
from rngcam.formats.bundle import bundle_checksum
from rngcam.recon.metrics_schema import check_metrics
from rngcam.recon.settings import ReconSettings
from rngcam.sweeps import tables
from rngcam.sweeps.backend import Backend, make_backend
from rngcam.untrusted import load_json, read_untrusted, write_new

DONE_NAME = "batch-done.json"
SKIPPED_NOTE = "done before (skipped)"
METRIC_KEYS = ("seconds", "iterations", "psnr_db", "psnr_intermediate_db", "ssim", "residual_rs", "residual_gs")
COLUMNS = ["bundle", "status", *METRIC_KEYS, "out", "note"]


@dataclass
class BatchResult:
    rows: list[dict]
    out_dir: Path
    backend: str
    ran: int
    skipped: int
    failed: int


def _stamp(checksum: str, settings: ReconSettings) -> dict:
    s = asdict(settings)
    for volatile in ("progress", "resume", "overwrite", "log_every_s", "checkpoint_every_s"):
        s.pop(volatile, None)
    return {"bundle_sha256": checksum, "settings": s}


def _destinations(bundles: list[Path], out: Path) -> list[Path]:
    """<out>/<stem>, with a short path hash when two bundles share a stem."""
    stems = [b.stem for b in bundles]
    dests = []
    for b in bundles:
        name = b.stem
        if stems.count(b.stem) > 1:
            name += "-" + hashlib.sha256(str(b.resolve()).encode()).hexdigest()[:6]
        dests.append(out / name)
    return dests


def batch_task(item: dict, shared: object = None) -> dict:
    """Reconstruct one bundle (a Ray task or an in-process call); never raises."""
    lines: list[str] = []
    t0 = time.perf_counter()
    try:
        settings = item["settings"]
        asked = {"threads": item["threads"]} if item.get("threads") else {}  # the run sets and restores them
        result = reconstruct(item["bundle"], settings.method, out=item["out"], progress=lines.append, bar=False,
                             **{**keywords(settings), **asked})
        if result.status == "failed":
            raise RngcamError(f"{result.message}; outputs from the last good state are in {item['out']}")
        write_new(Path(item["out"]) / DONE_NAME, json.dumps(item["stamp"]))
        res = {"status": "ok", "message": "", **{k: result.metrics.get(k) for k in METRIC_KEYS}}
    except RngcamError as exc:
        res = {"status": "failed", "message": str(exc)}
    except Exception as exc:  # noqa: BLE001 - one bundle must not stop the batch
        res = {"status": "failed", "message": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    res["wall_s"] = time.perf_counter() - t0
    res["log"] = lines[-20:]
    return res


def recon_batch(bundles: list[str | Path], out_dir: str | Path, settings: ReconSettings | None = None,
                backend_factory: Callable[[], Backend] | None = None, task_fn=batch_task,
                echo: Callable[[str], None] = print) -> BatchResult:
    """Reconstruct every bundle with `settings` (see the module docstring)."""
    # A bundle not done with these settings is redone from scratch, over whatever an earlier run left.
    given = settings or ReconSettings()
    settings = replace(given, progress=False, resume=False, overwrite=True)  # "auto" stays auto: per bundle
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [Path(b) for b in bundles]
    dests = _destinations(paths, out)
    rows: list[dict] = []
    todo: list[tuple[int, dict]] = []
    for path, dest in zip(paths, dests):
        row = {"bundle": str(path), "out": str(dest), "status": "", "note": ""}
        rows.append(row)
        try:
            stamp = _stamp(bundle_checksum(path), settings)
        except RngcamError as exc:
            row.update(status="failed", note=str(exc))
            continue
        done = _read_json(dest / DONE_NAME)
        metrics = _read_json(dest / "metrics.json") if done == stamp else None
        if metrics is not None:
            row.update(status="ok", note=SKIPPED_NOTE, **{k: metrics.get(k) for k in METRIC_KEYS})
            continue
        todo.append((len(rows) - 1, {"bundle": str(path), "out": str(dest), "stamp": stamp,
                                     "settings": settings}))
    backend_name = "none (nothing to do)"
    if todo:
        backend = (backend_factory or (lambda: make_backend(echo=echo)))()
        backend_name = backend.name
        echo(f"{len(todo)} bundle(s) to reconstruct on {backend_name}, {len(rows) - len(todo)} skipped or unreadable")
        items = [{**item, "threads": backend.threads_per_task} for _, item in todo]

        def report(j: int, res: dict) -> None:
            name = Path(items[j]["bundle"]).name
            echo(f"  {name}: " + (f"done in {res.get('seconds') or 0:.1f} s" if res["status"] == "ok"
                                  else f"FAILED: {res.get('message', '')}"))

        try:
            results = backend.map(task_fn, items, None, on_result=report)
        finally:
            backend.close()
        for (i, _), res in zip(todo, results):
            rows[i].update(status=res["status"], note=res.get("message", ""),
                           **{k: res.get(k) for k in METRIC_KEYS})
    tables.write_csv(out / "batch.csv", rows, COLUMNS)
    fmt = {"seconds": lambda v: "-" if v is None else f"{v:.1f}", "psnr_db": lambda v: "-" if v is None else f"{v:.2f}"}
    md = tables.markdown([{**r, "bundle": Path(r["bundle"]).name, "out": Path(r["out"]).name} for r in rows],
                         COLUMNS, fmt)
    tables.write_text(out / "batch.md", f"# Batch reconstruction ({settings.method})\n\n{md}")
    ran = sum(rows[i]["status"] == "ok" for i, _ in todo)  # reconstructed now; failures are counted apart
    return BatchResult(rows=rows, out_dir=out, backend=backend_name, ran=ran,
                       skipped=sum(r["note"] == SKIPPED_NOTE for r in rows),
                       failed=sum(r["status"] != "ok" for r in rows))


def _read_json(path: Path):
    """A JSON file of an output folder (by descriptor: a link, FIFO or device is None, never
    followed or waited on); None when absent or unreadable. metrics.json's fields are checked
    against its schema (None when one is off: the bundle is reconstructed again)."""
    try:
        value = load_json(read_untrusted(path, 16 << 20, what="JSON file", within=path.parent), str(path))
        return check_metrics(value, str(path)) if path.name == "metrics.json" else value
    except (RngcamError, ValueError):
        return None
