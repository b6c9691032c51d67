"""One sweep trial: fit one setting on a training split, score it on the held-out split.

With several folds (held-out splits at different places, Problem.with_holdout(fold=j)) the
trial fits once per fold and reports the mean of every figure: a steadier score than one small
held-out set.
`run_trial` is a plain function of picklable arguments, so it runs the same in-process or as a
Ray task. Each fold keeps a checkpoint in the trial's folder and resumes from it: a later
(longer) rung of successive halving, or a retry after a killed worker, continues where it stopped.
"""

from __future__ import annotations

import math
import os
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from rngcam.cpu import torch_threads
from rngcam.errors import RngcamError
from rngcam.recon import checkpoint
from rngcam.recon.checkpoint import CHECKPOINT_NAME
from rngcam.recon.holdout import HoldoutScorer
from rngcam.recon.metrics import video_metrics
from rngcam.recon.problem import Problem
from rngcam.recon.runner import fit_checkpointed, resolve_device
from rngcam.recon.settings import Clock, ReconSettings, resolve
from rngcam.untrusted import clean_temps

TRUTH_KEYS = ("psnr_db", "ssim", "psnr_intermediate_db", "ssim_intermediate")


@dataclass(frozen=True)
class TrialSpec:
    """What to fit and for how long. `key` names the setting (not the budget)."""

    key: str
    method: str
    settings: Any = None  # the method's settings (rngcam.recon.registry; None: its default preset)
    max_iters: int | None = None
    time_budget_s: float | None = None  # per fold
    trial_dir: str = ""
    holdout_rs: float = 0.1  # Problem.with_holdout fractions
    holdout_gs: float = 0.0
    seed: int = 0  # split seed; fold j is Problem.with_holdout(..., seed, fold=j, folds=folds)
    folds: int = 1
    device: str = "cpu"
    threads: int | None = None  # torch threads inside the trial (None: leave as is)


def _resumable(path: Path, spec: TrialSpec, want: dict) -> dict | None:
    """The checkpoint a trial continues (a later rung), or None. One from a longer run than this
    budget (an earlier sweep) cannot be resumed and is dropped. One that is not data only, or not
    this trial's, is refused in one line (the trial fails, nothing runs)."""
    if not os.path.lexists(path):
        return None
    saved = checkpoint.load(path, hint=checkpoint.RESUME_HINT)
    why = checkpoint.mismatch(saved, want)
    if why:
        raise RngcamError(f"cannot resume from {path}: {why}; {checkpoint.RESUME_HINT}")
    if (spec.max_iters is not None and saved["iteration"] > spec.max_iters) or (
            spec.time_budget_s is not None and saved["wall_s"] > spec.time_budget_s):
        path.unlink(missing_ok=True)
        return None
    return saved


def run_trial(spec: TrialSpec, problem: Problem) -> dict:
    """Fit `spec` on `problem` (all measurements; the trial draws its splits); never raises.

    Returns the trial's figures, averaged over folds: iterations, seconds (solve time of all
    folds and rungs), training residuals, held-out scores, truth metrics when the problem has
    truth, and status/message.
    """
    out = {"key": spec.key, "status": "ok", "message": ""}
    try:
        with torch_threads(spec.threads or torch.get_num_threads()):
            device = resolve_device(spec.device)
            folds = [_fit_fold(spec, problem.with_holdout(spec.holdout_rs, spec.holdout_gs, spec.seed, fold=j,
                                                          folds=spec.folds),
                               Path(spec.trial_dir) / (f"fold-{j}" if spec.folds > 1 else ""), device)
                     for j in range(spec.folds)]
            failed = [f for f in folds if f["status"] != "ok"]
            out.update(status="failed" if failed else "ok", message=failed[0]["message"] if failed else "")
            numbers = [k for k in folds[0] if k not in ("status", "message") and all(k in f for f in folds)]
            out.update({k: sum(f[k] for f in folds) / len(folds) for k in numbers})
            out["iterations"] = folds[0]["iterations"]
            out["seconds"] = sum(f["seconds"] for f in folds)
    except Exception as exc:  # noqa: BLE001 - a failed trial is a row in the table, not the end of the sweep
        out.update(status="failed", message=f"{type(exc).__name__}: {exc}".splitlines()[0])
        out["traceback"] = traceback.format_exc(limit=5)
    return out


def _fit_fold(spec: TrialSpec, problem: Problem, folder: Path, device: str) -> dict:
    """One fit on `problem`'s training split, resumed from `folder`; its figures. It runs as any
    run does (rngcam.recon.runner): its settings resolved, its method built on its own clock."""
    folder.mkdir(parents=True, exist_ok=True)
    clean_temps(folder)  # a killed worker's half-written checkpoint
    want = checkpoint.identity(None, spec.method, {"trial": spec.key, "fold": folder.name})
    saved = _resumable(folder / CHECKPOINT_NAME, spec, want)
    # A later rung extends the fit: its budget is the fit's total, so the clock counts the earlier rungs.
    clock = Clock(time.perf_counter() - (saved["wall_s"] if saved else 0.0))
    settings = ReconSettings(method=spec.method, method_settings=spec.settings, device=device,
                             time_budget_s=spec.time_budget_s, max_iters=spec.max_iters, log_every_s=math.inf,
                             checkpoint_every_s=10.0, progress=False)
    video, result = fit_checkpointed(problem, resolve(settings, problem.shape, clock, finish=False), folder, want,
                                     saved)
    final = result.log[-1] if result.log else {}
    out = {"iterations": result.iterations, "seconds": result.solve_s, "status": result.status,
           "message": result.message, **{k: v for k, v in final.items() if k.startswith("residual_")}}
    video = video.double().cpu()
    reference = problem.to(torch.float64, "cpu")
    out.update(HoldoutScorer(reference)(video))
    if reference.truth is not None:
        out.update(video_metrics(video, reference.truth, reference.intermediate_frames(), reference.mask))
    return out
