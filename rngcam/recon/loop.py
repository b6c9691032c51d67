"""The one solver loop every iterative method uses.

It runs `method.step()` until a wall-clock budget and/or an iteration count is reached; logs
time, objective, per-sensor relative residuals and, with truth, PSNR/SSIM (all frames and
intermediate frames) at regular intervals; shows a progress bar; checkpoints and resumes; and
guards against NaN/Inf by rolling back to the last good state with a smaller step.

Time: `wall_s` is elapsed wall-clock time since the start (the budget applies to it); `solve_s`
is the time spent inside `step()` only, excluding metric evaluation and checkpoints. Error
against run time is reported against `solve_s`, the reconstruction's own cost.
"""

from __future__ import annotations

import copy
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

CHECKPOINT_NAME = "checkpoint.pt"


class Method(Protocol):
    """What the loop and the runner need from an iterative method (MethodBase gives the defaults
    of everything below `reduce_step`)."""

    name: str
    supports_holdout: bool  # fits only the training split of Problem.with_holdout
    stops_itself: bool  # has a stop of its own (`converged`), so a budget may cut it short
    left_out: list[tuple[str, str]]  # (component or measurement, why) the method dropped
    notes: list[str]  # substitutions it made (e.g. missing learned weights) and their cost

    def step(self) -> float:
        """One iteration; returns the objective value (may be a stochastic estimate)."""

    def estimate(self) -> Tensor:
        """Current video (C, K, H, W)."""

    def residuals(self) -> dict[str, float]:
        """Relative data residual per sensor, e.g. {"rs": 0.1, "gs": 0.02}."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...

    def reduce_step(self, factor: float) -> None:
        """Shrink the step size / learning rate after a NaN or Inf."""

    def converged(self) -> str | None:
        """Asked after every step; a reason ends the run early (e.g. STFM's discrepancy-principle
        stop) and is kept in the events."""

    def budget_cut(self) -> str:
        """What a time budget cut short (e.g. "levels 2-3 of 3 not reached"), or ''."""

    def components(self) -> dict:
        """Named parts of the result (e.g. STFM's static image and alpha) for recon.h5."""

    def resolved_settings(self) -> dict | None:
        """The settings with every preset value filled in, for metrics.json (None: nothing to add)."""


class MethodBase:
    """The defaults of Method's optional parts: no held-out fitting, no stop of its own, nothing
    left out, no notes, no components, no resolved settings."""

    supports_holdout = False
    stops_itself = False
    left_out: list[tuple[str, str]] = []  # noqa: RUF012 - read-only default; methods assign their own
    notes: list[str] = []  # noqa: RUF012

    def converged(self) -> str | None:
        return None

    def budget_cut(self) -> str:
        return ""

    def components(self) -> dict:
        return {}

    def resolved_settings(self) -> dict | None:
        return None


@dataclass
class LoopSettings:
    time_budget_s: float | None = 60.0
    max_iters: int | None = None
    log_every_s: float = 2.0
    log_every_iters: int | None = None
    checkpoint_dir: Path | None = None
    checkpoint_every_s: float = 60.0
    resume: bool = False
    max_failures: int = 5
    progress: bool = True
    progress_every_s: float = 10.0  # without a terminal: one progress line this often (stderr)

    def __post_init__(self):
        if self.time_budget_s is None and self.max_iters is None:
            raise ValueError("set a time budget, an iteration count, or both")
        if self.time_budget_s is not None and not (self.time_budget_s > 0 and math.isfinite(self.time_budget_s)):
            raise ValueError(f"time budget must be a positive number of seconds, got {self.time_budget_s}")
        if self.max_iters is not None and self.max_iters < 0:
            raise ValueError(f"iteration count must be >= 0, got {self.max_iters}")


@dataclass
class RunResult:
    log: list[dict]
    iterations: int
    solve_s: float
    wall_s: float
    events: list[str] = field(default_factory=list)
    status: str = "ok"  # "ok" or "failed"
    message: str = ""


def _finite_state(state) -> bool:
    if isinstance(state, Tensor):
        return bool(torch.isfinite(state).all()) if state.is_floating_point() else True
    if isinstance(state, dict):
        return all(_finite_state(v) for v in state.values())
    if isinstance(state, (list, tuple)):
        return all(_finite_state(v) for v in state)
    if isinstance(state, float):
        return math.isfinite(state)
    return True


def _save_checkpoint(path: Path, payload: dict) -> None:
    tmp = path.with_name(path.name + ".partial")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def run(method: Method, settings: LoopSettings,
        evaluate: Callable[[Method], dict[str, float]] | None = None, setup_s: float = 0.0) -> RunResult:
    """Iterate `method` under `settings`; `evaluate(method)` adds truth metrics to each log row.

    `setup_s` is the time the method took to build (operator norms, initialisation): it counts
    as solve time. Logs are spaced so that evaluation costs at most ~20 % of the run.
    """
    log: list[dict] = []
    events: list[str] = []
    iteration, solve_s, wall_offset = 0, float(setup_s), 0.0
    ckpt = None if settings.checkpoint_dir is None else Path(settings.checkpoint_dir) / CHECKPOINT_NAME
    if settings.resume and ckpt is not None and ckpt.is_file():
        saved = torch.load(ckpt, weights_only=False)
        method.load_state_dict(saved["method"])
        iteration, solve_s, wall_offset = saved["iteration"], saved["solve_s"], saved["wall_s"]
        log, events = saved["log"], saved["events"] + [f"resumed from {ckpt.name} at iteration {iteration}"]
        torch.set_rng_state(saved["rng"])

    start = time.perf_counter() - wall_offset - (setup_s if not log else 0.0)
    last_good = (copy.deepcopy(method.state_dict()), iteration, solve_s)
    failures, objective = 0, float("nan")
    last_log_solve, eval_s, last_ckpt_t = -math.inf, 0.0, time.perf_counter()

    def wall() -> float:
        return time.perf_counter() - start

    def done() -> bool:
        if settings.max_iters is not None and iteration >= settings.max_iters:
            return True
        return settings.time_budget_s is not None and wall() >= settings.time_budget_s

    def record(obj: float) -> dict:
        nonlocal eval_s
        t0 = time.perf_counter()
        row = {"iteration": iteration, "wall_s": wall(), "solve_s": solve_s, "objective": obj}
        row.update({f"residual_{k}": v for k, v in method.residuals().items()})
        if evaluate is not None:
            row.update(evaluate(method))
        log.append(row)
        eval_s = time.perf_counter() - t0
        return row

    def checkpoint() -> None:
        if ckpt is None:
            return
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        _save_checkpoint(ckpt, {"method": method.state_dict(), "iteration": iteration,
                                "solve_s": solve_s, "wall_s": wall(), "log": log,
                                "events": events, "rng": torch.get_rng_state()})

    stop_reason = None
    with _progress(settings, method.name) as bar:
        if not log:
            record(float("nan"))
        while not done() and stop_reason is None:
            t0 = time.perf_counter()
            objective = float(method.step())
            solve_s += time.perf_counter() - t0
            iteration += 1
            due = (settings.log_every_iters is not None and iteration % settings.log_every_iters == 0) or (
                settings.log_every_iters is None
                and solve_s - last_log_solve >= max(settings.log_every_s, 4 * eval_s))
            ckpt_due = ckpt is not None and time.perf_counter() - last_ckpt_t >= settings.checkpoint_every_s
            # A non-finite state shows in the next objective; the whole state is checked only
            # where it is kept (log snapshot, checkpoint, the end), not after every step.
            bad, state = not math.isfinite(objective), None
            if not bad and method.stops_itself:
                stop_reason = method.converged()
            if not bad and (due or ckpt_due or done() or stop_reason):
                state = method.state_dict()
                bad = not _finite_state(state)
            if bad:
                failures += 1
                good, iteration, solve_s = last_good
                method.load_state_dict(copy.deepcopy(good))
                method.reduce_step(0.5)
                events.append(f"non-finite state at iteration {iteration + 1}: rolled back, step halved "
                              f"(failure {failures} of {settings.max_failures})")
                if failures >= settings.max_failures:
                    record(float("nan"))
                    return RunResult(log, iteration, solve_s, wall(), events, "failed",
                                     f"{method.name}: {failures} non-finite steps in a row; "
                                     f"kept the last good state (iteration {iteration})")
                stop_reason = None
                continue
            failures = 0
            if due:
                last_log_solve = solve_s
                bar.show(record(objective), iteration, wall())
                last_good = (copy.deepcopy(state), iteration, solve_s)
            if ckpt_due:
                checkpoint()
                last_ckpt_t = time.perf_counter()
        if stop_reason:
            events.append(f"stopped at iteration {iteration}: {stop_reason}")
        elif settings.time_budget_s is not None and wall() >= settings.time_budget_s and (
                settings.max_iters is None or iteration < settings.max_iters):
            events.append(budget_event(method, settings.time_budget_s, iteration, setup_s))
        if not log or log[-1]["iteration"] != iteration:
            bar.show(record(objective), iteration, wall())
        checkpoint()
    return RunResult(log, iteration, solve_s, wall(), events)


def budget_event(method, budget_s: float, iteration: int, setup_s: float) -> str:
    """The event that says the time budget, not the method, ended a run, and what was cut."""
    name = method.name
    what = method.budget_cut()
    head = f"time budget of {budget_s:g} s reached at iteration {iteration}"
    if setup_s >= budget_s:
        head += f" (set-up alone took {setup_s:.1f} s)"
    elif setup_s > 0:
        head += f" (set-up {setup_s:.1f} s)"
    why = (f"before {name}'s own stop" if method.stops_itself
           else f"{name} has no stop of its own, so the budget decides how far it gets")
    cut = f"; cut: {what}" if what else ""
    return (f"{head}, {why}{cut}; the state at the budget is written (a larger --time-budget with "
            f"--resume may improve it)")


def is_terminal(stream=None) -> bool:
    stream = stream or sys.stderr
    return bool(getattr(stream, "isatty", lambda: False)())


def stage_printer(echo=None, enabled: bool = True):
    """A callable `stage(message)` that prints 'set-up: message (t s)' with the time since it was made,
    so every set-up stage shows progress in a terminal and in a log alike."""
    t0 = time.perf_counter()
    echo = echo or (lambda line: print(line, file=sys.stderr, flush=True))

    def stage(message: str) -> None:
        if enabled:
            echo(f"set-up: {message} ({time.perf_counter() - t0:.1f} s)")
    return stage


class _progress:
    """A rich progress bar showing the latest figures in a terminal; without one, a plain line
    every `progress_every_s` seconds on stderr (so a log file shows the run as it goes); silent
    when progress=False."""

    def __init__(self, settings: LoopSettings, name: str):
        self.settings, self.name, self._bar, self._task = settings, name, None, None
        self._lines = settings.progress and not is_terminal()
        self._last_line = -math.inf

    def __enter__(self):
        if self.settings.progress and not self._lines:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                                 TextColumn("{task.fields[figures]}"), transient=False)
            total = self.settings.time_budget_s or self.settings.max_iters
            self._task = self._bar.add_task(self.name, total=total, figures="")
            self._bar.start()
        return self

    def show(self, row: dict, iteration: int, wall_s: float) -> None:
        figs = f"it {iteration}  obj {row['objective']:.4g}"
        if "psnr_db" in row:
            figs += f"  PSNR {row['psnr_db']:.2f} dB"
        if self._lines:
            if wall_s - self._last_line >= self.settings.progress_every_s:
                self._last_line = wall_s
                budget = f" of {self.settings.time_budget_s:g} s" if self.settings.time_budget_s else ""
                print(f"{self.name}: {wall_s:.0f} s{budget}  {figs}", file=sys.stderr, flush=True)
            return
        if self._bar is None:
            return
        done = wall_s if self.settings.time_budget_s else iteration
        self._bar.update(self._task, completed=done, figures=figs)

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.stop()
        return False
