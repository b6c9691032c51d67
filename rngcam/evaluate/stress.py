"""`rngcam bench --stress`: run every stress case through the operators and a short run of each
method, and classify each (case, method) as

- ``finite``: ran and gave a finite video (and, for tv3d with restart, a monotone objective);
- ``rejected``: refused with a clear error (an RngcamError; a ValueError too when the case
  calls the library directly rather than through a bundle), for inputs that must be refused;
- ``FAILED``: NaN/Inf output, a crash or traceback, a broken promise (non-monotone tv3d,
  adjoint mismatch, float32 far from float64), a refusal of a valid input, or an invalid
  input accepted.

Operator rows (method "operators") check <A x, y> = <x, A^T y> in float64 and the relative
difference between float32 and float64 forward and adjoint results, for the RS and GS operators.
"""

from __future__ import annotations

import itertools
import json
import math
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from rngcam.api import reconstruct
from rngcam.errors import RngcamError
from rngcam.evaluate import report
from rngcam.evaluate.stress_cases import ALL_METHODS, StressCase, stress_cases
from rngcam.formats.bundle import read_bundle
from rngcam.physics.operators import inner
from rngcam.recon import registry
from rngcam.recon.metrics import psnr
from rngcam.recon.problem import Problem, build_problem

ADJOINT_TOL = 1e-9  # relative, float64
FP32_TOL = 1e-4  # relative difference float32 vs float64
MONOTONE_TOL = 1e-9  # relative increase of the objective tolerated (rounding)
EXACT_PROX_MAX_ELEMENTS = 10_000  # tv3d with the exact prox only on videos up to this size


@dataclass(frozen=True)
class StressSettings:
    """How long each short run is: iterations and a wall-clock cap (seconds) per method run."""

    tv3d_iters: int = 15
    tv3d_exact_iters: int = 3  # the exact prox costs ~0.2-1 s per call even on tiny videos
    stfm_iters: int = 5
    time_cap_s: float = 30.0


def available_methods() -> list[str]:
    """Methods installed here (RIFE needs its weights)."""
    return [m for m in ALL_METHODS if not registry.unavailable(m)]


# ----------------------------------------------------------------------------- operators


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    den = float(torch.linalg.vector_norm(b))
    num = float(torch.linalg.vector_norm((a - b).double()))
    return 0.0 if num == 0 else (num / den if den > 0 else math.inf)


def check_operators(problem: Problem) -> dict:
    """Adjoint identity (float64) and float32-vs-float64 differences of the RS and GS operators."""
    p64, p32 = problem.to(torch.float64), problem.to(torch.float32)
    gen = torch.Generator().manual_seed(0)
    out = {"adjoint_err": 0.0, "fp32_diff": 0.0, "finite": True}
    video = problem.truth if problem.truth is not None else torch.rand(problem.shape, generator=gen)
    ops = [("rs", p64.rs_op(), p32.rs_op())]
    if problem.b_gs is not None and problem.b_gs.shape[1]:
        ops.append(("gs", p64.gs_op(), p32.gs_op()))
    for _, op64, op32 in ops:
        x = torch.randn(problem.shape, generator=gen, dtype=torch.float64)
        ax = op64.A(x)
        y = torch.randn(ax.shape, generator=gen, dtype=torch.float64)
        aty = op64.A_adjoint(y)
        lhs, rhs = float(inner(ax, y)), float(inner(x, aty))
        scale = max(float(ax.norm() * y.norm()), float(x.norm() * aty.norm()), 1e-300)
        out["adjoint_err"] = max(out["adjoint_err"], abs(lhs - rhs) / scale)
        b64 = op64.A(video.double())
        b32 = op32.A(video.float())
        back64 = op64.A_adjoint(b64)
        back32 = op32.A_adjoint(b64.float())
        out["fp32_diff"] = max(out["fp32_diff"], _rel(b32, b64), _rel(back32, back64))
        out["finite"] &= all(bool(torch.isfinite(t).all()) for t in (ax, aty, b64, b32, back64, back32))
    return out


def operator_row(problem: Problem) -> dict:
    r = check_operators(problem)
    problems = []
    if not r["finite"]:
        problems.append("non-finite operator output")
    if not r["adjoint_err"] <= ADJOINT_TOL:
        problems.append(f"adjoint mismatch {r['adjoint_err']:.2e}")
    if not r["fp32_diff"] <= FP32_TOL:
        problems.append(f"float32 differs from float64 by {r['fp32_diff']:.2e}")
    return {"outcome": "FAILED" if problems else "finite", "adjoint_err": r["adjoint_err"],
            "fp32_diff": r["fp32_diff"], "message": "; ".join(problems)}


# ----------------------------------------------------------------------------- methods through the API


def monotone(objectives: list[float]) -> tuple[bool, float]:
    """(non-increasing up to rounding, largest relative increase) of the finite objectives."""
    vals = [v for v in objectives if isinstance(v, float) and math.isfinite(v)]
    worst = 0.0
    for a, b in itertools.pairwise(vals):
        worst = max(worst, (b - a) / max(abs(a), 1e-300))
    return worst <= MONOTONE_TOL, worst


def _iterations(method: str, settings: StressSettings) -> int | None:
    if method == "tv3d-exact":
        return settings.tv3d_exact_iters
    if method.startswith("tv3d"):
        return settings.tv3d_iters
    return settings.stfm_iters if method.startswith("stfm") else None


def _short_run(source, method: str, options: dict, settings: StressSettings, out: Path | None = None) -> dict:
    """A short `rngcam.reconstruct` of `source` (a Problem or a bundle path): {video, iterations,
    objectives, status, message}; every logged iteration's objective (a subsequence is monotone
    when the run is)."""
    where = {"overwrite": True} if out is not None else {"device": "cpu"}
    result = reconstruct(source, method, out=out, progress=False, time_budget_s=settings.time_cap_s,
                         max_iters=_iterations(method, settings), log_every_s=0.0, checkpoint_every_s=1e9,
                         **where, **options)
    if result.status == "failed" and out is not None:  # as `rngcam recon` reports it: one error line
        raise RngcamError(f"{result.message}; outputs from the last good state are in {out}")
    return {"video": torch.from_numpy(result.video), "iterations": result.metrics["iterations"],
            "objectives": [r["objective"] for r in result.log], "status": result.status,
            "message": "; ".join([result.message, *result.metrics["events"]]).strip("; "),
            "psnr_db": result.metrics.get("psnr_db")}


def run_on_problem(problem: Problem, method: str, options: dict, settings: StressSettings) -> dict:
    """Short run of `method` on `problem`: {video, iterations, objectives, status, message}."""
    return _short_run(problem, method, options, settings)


def run_on_bundle(bundle: Path, method: str, options: dict, settings: StressSettings, out: Path) -> dict:
    """`reconstruct` the bundle (the user's path) into `out`, every output written."""
    return _short_run(bundle, method, options, settings, out)


# ----------------------------------------------------------------------------- classification


def classify(expect: str, method: str, outcome_of: Callable[[], dict], clear: tuple[type, ...]) -> dict:
    """Run `outcome_of()` and turn what happened into a result row (see module docstring)."""
    row: dict = {}
    t0 = time.perf_counter()
    try:
        got = outcome_of()
    except clear as exc:
        row["seconds"] = time.perf_counter() - t0
        if expect == "reject":
            return {**row, "outcome": "rejected", "message": f"{type(exc).__name__}: {exc}"}
        return {**row, "outcome": "FAILED", "message": f"refused a valid input: {type(exc).__name__}: {exc}"}
    except Exception as exc:  # noqa: BLE001 - a crash is the finding
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        where = f"{Path(tb.filename).name}:{tb.lineno}"
        return {"seconds": time.perf_counter() - t0, "outcome": "FAILED",
                "message": f"crash {type(exc).__name__} at {where}: {exc}"}
    row["seconds"] = time.perf_counter() - t0
    if "outcome" in got:  # operator rows classify themselves
        if expect == "reject" and got["outcome"] == "finite":
            got = {**got, "outcome": "FAILED", "message": "invalid input accepted"}
        return {**row, **got}
    video = got["video"]
    finite = bool(torch.isfinite(video).all())
    row.update(iterations=got["iterations"], out_min=float(video.min()) if finite else math.nan,
               out_max=float(video.max()) if finite else math.nan)
    if got.get("psnr_db") is not None:
        row["psnr_db"] = got["psnr_db"]
    problems = []
    if not finite:
        problems.append("non-finite output")
    if got["status"] != "ok":
        problems.append(f"loop status {got['status']}")
    if method.startswith("tv3d") and got["objectives"]:
        ok, worst = monotone(got["objectives"])
        row["monotone"] = ok
        row["max_rise"] = worst
        if not ok:
            problems.append(f"objective rose by {worst:.2e} (relative) with restart on")
    if expect == "reject":
        problems.append("invalid input accepted")
    note = "; ".join(problems + ([got["message"]] if got.get("message") else []))
    return {**row, "outcome": "FAILED" if problems else "finite", "message": note}


def _psnr(problem: Problem | None, video) -> float | None:
    if problem is None or problem.truth is None or not bool(torch.isfinite(video).all()):
        return None

    return psnr(video.double(), problem.truth)


def run_case(case: StressCase, methods: list[str], settings: StressSettings, out: Path) -> list[dict]:
    """All rows of one case: operators first, then each method the case concerns."""
    base = {"case": case.name, "group": case.group, "expect": case.expect}
    rows: list[dict] = []
    problem, bundle_path = None, None
    clear: tuple[type, ...] = (RngcamError,) if case.bundle else (RngcamError, ValueError)
    if case.bundle:
        try:
            (out / "bundles").mkdir(parents=True, exist_ok=True)
            bundle_path = case.write_bundle(out / "bundles" / f"{_slug(case.name)}.h5")
        except Exception as exc:  # noqa: BLE001 - the harness's own failure, reported not raised
            return [{**base, "method": "bundle", "outcome": "FAILED",
                     "message": f"could not write the case's bundle: {type(exc).__name__}: {exc}"}]

    def operators():
        nonlocal problem
        problem = build_problem(read_bundle(bundle_path)) if case.bundle else case.problem()
        return operator_row(problem)

    rows.append({**base, "method": "operators", "expect": case.expect_operators,
                 **classify(case.expect_operators, "operators", operators, clear)})
    for method in methods:
        if method not in case.methods:
            continue
        if method == "tv3d-exact" and problem is not None and math.prod(problem.shape) > EXACT_PROX_MAX_ELEMENTS:
            continue
        if case.bundle:
            target = out / "runs" / _slug(case.name) / method

            def go(m=method, t=target):
                return run_on_bundle(bundle_path, m, case.options, settings, t)
        else:
            def go(m=method):
                if problem is None:  # the case itself could not be built: same error again
                    case.problem()
                got = run_on_problem(problem, m, case.options, settings)
                return {**got, "psnr_db": _psnr(problem, got["video"])}
        rows.append({**base, "method": method, **classify(case.expect, method, go, clear)})
    return rows


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip("_")


def run_stress(out: Path, settings: StressSettings | None = None, cases: list[StressCase] | None = None,
               methods: list[str] | None = None, echo=print) -> list[dict]:
    """Run the matrix (all cases and installed methods unless given); write results.csv/.md."""
    settings = settings or StressSettings()
    out = Path(out)
    (out / "bundles").mkdir(parents=True, exist_ok=True)
    cases = stress_cases() if cases is None else cases
    methods = available_methods() if methods is None else methods
    rows: list[dict] = []
    t0 = time.perf_counter()
    for case in cases:
        case_rows = run_case(case, methods, settings, out)
        rows += case_rows
        bad = [r["method"] for r in case_rows if r["outcome"] == "FAILED"]
        echo(f"{case.name:28s} " + " ".join(f"{r['method']}:{r['outcome']}" for r in case_rows)
             + (f"   <-- FAILED: {', '.join(bad)}" if bad else ""))
    elapsed = time.perf_counter() - t0
    write_report(out, rows, methods, settings, elapsed)
    return rows


STRESS_COLUMNS = ["case", "group", "method", "expect", "outcome", "seconds", "iterations", "psnr_db",
                  "out_min", "out_max", "monotone", "max_rise", "adjoint_err", "fp32_diff", "message"]


def summary_counts(rows: list[dict]) -> dict[str, int]:
    counts = {"finite": 0, "rejected": 0, "FAILED": 0}
    for r in rows:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    return counts


def write_report(out: Path, rows: list[dict], methods: list[str], settings: StressSettings,
                 elapsed_s: float) -> None:
    """results.csv (every column) and results.md (summary, failures first, then every row)."""
    report.write_csv(out / "results.csv", rows, STRESS_COLUMNS)
    counts = summary_counts(rows)
    failed = [r for r in rows if r["outcome"] == "FAILED"]
    md = ["# rngcam bench --stress", "",
          (f"{len(rows)} rows: **{counts['finite']} finite, {counts['rejected']} rejected, "
           f"{counts['FAILED']} FAILED** ({elapsed_s:.0f} s)."), "",
          (f"Methods: {', '.join(methods)}. Short runs: tv3d {settings.tv3d_iters} iterations "
           f"({settings.tv3d_exact_iters} with the exact prox), STFM {settings.stfm_iters} steps "
           f"(after its set-up), each capped at {settings.time_cap_s:g} s."),
          (f"Operators: adjoint identity within {ADJOINT_TOL:g} (float64), float32 within "
           f"{FP32_TOL:g} of float64 (relative). tv3d runs with restart and must not raise its "
           f"objective (tolerance {MONOTONE_TOL:g} relative). tv3d with the exact prox runs on videos "
           f"up to {EXACT_PROX_MAX_ELEMENTS:,} values. GS-only baselines run only on cases that "
           "change their input (data, timing, size)."), ""]
    if failed:
        md += ["## FAILED", "", report.markdown_table(failed, ["case", "method", "message"]), ""]
    md += ["## All rows", "",
           report.markdown_table(rows, ["case", "method", "expect", "outcome", "seconds", "iterations",
                                        "psnr_db", "monotone", "adjoint_err", "fp32_diff", "message"],
                                 {"psnr_db": "PSNR dB", "adjoint_err": "adjoint err",
                                  "fp32_diff": "fp32 vs fp64"}), ""]
    (out / "results.md").write_text("\n".join(md))
    (out / "summary.json").write_text(json.dumps(counts))
