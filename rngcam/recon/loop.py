"""The one solver loop every iterative method uses.

It runs `method.step()` until the run's clock (rngcam.recon.loop.Clock) passes its deadline and/or
an iteration count is reached; logs
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
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from torch import Tensor

from rngcam.errors import RngcamError
from rngcam.recon import checkpoint
from rngcam.recon.checkpoint import CHECKPOINT_NAME, RESUME_HINT
from rngcam.recon.options import check_seconds


class Clock:
    """When a run started (a time.perf_counter()) and, once its budget is resolved, when its
    set-up and solve must end. One per run: everything that checks the time reads this one."""

    def __init__(self, start: float | None = None, seconds: float | None = None):
        self.start = time.perf_counter() if start is None else float(start)
        self.deadline: float | None = None
        if seconds is not None:
            self.limit(seconds)

    def limit(self, seconds: float | None) -> Clock:
        """Set the deadline `seconds` after the start (None: no deadline); once only."""
        if self.deadline is not None:
            raise RuntimeError("a run's clock gets its deadline once")
        self.deadline = None if seconds is None else self.start + float(seconds)
        return self

    @property
    def seconds(self) -> float | None:
        """The seconds from the start to the deadline (None: no deadline)."""
        return None if self.deadline is None else self.deadline - self.start

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> float | None:
        """Seconds left before the deadline (negative past it; None: no deadline)."""
        return None if self.deadline is None else self.deadline - time.perf_counter()

    def expired(self) -> bool:
        return self.deadline is not None and time.perf_counter() >= self.deadline

    def share(self, fraction: float) -> float | None:
        """`fraction` of what is left now: the seconds a stage that wants that share may take."""
        left = self.left()
        return None if left is None else max(0.0, fraction * left)

    def __repr__(self) -> str:
        return f"Clock(elapsed={self.elapsed():.1f} s, seconds={self.seconds})"


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

    def log_ready(self) -> bool:
        """Whether a log row now costs least (STFM: its stop test has just made the video the row
        scores); a row due by time waits for it."""

    def converged(self) -> str | None:
        """Asked after every step; a reason ends the run early (e.g. STFM's discrepancy-principle
        stop) and is kept in the events."""

    def budget_cut(self) -> str:
        """What a time budget cut short (e.g. "levels 2-3 of 3 not reached"), or ''."""

    def components(self) -> dict:
        """Named parts of the result (e.g. STFM's static image and alpha) for recon.h5."""

    def resolved_settings(self) -> dict | None:
        """The settings with every preset value filled in, for metrics.json (None: nothing to add)."""

    def end_fit(self) -> None:
        """The loop is over and the video taken: what only steps need (gradients, an optimiser's
        state) and cached videos may go; estimate(), components() and the reports still work."""


class MethodBase:
    """The defaults of Method's optional parts: no held-out fitting, no stop of its own, nothing
    left out, no notes, no components, no resolved settings."""

    supports_holdout = False
    stops_itself = False
    left_out: list[tuple[str, str]] = []  # noqa: RUF012 - read-only default; methods assign their own
    notes: list[str] = []  # noqa: RUF012

    def converged(self) -> str | None:
        return None

    def log_ready(self) -> bool:
        return True

    def budget_cut(self) -> str:
        return ""

    def components(self) -> dict:
        return {}

    def resolved_settings(self) -> dict | None:
        return None

    def end_fit(self) -> None:
        return None


class Wrapped(MethodBase):
    """A method around another (`self._method`, set by the subclass): every part it does not define is the
    inner method's, MethodBase's defaults included (they would hide the inner method's own)."""

    _method: Method

    def __getattr__(self, name):
        if name.startswith("__") or name == "_method":
            raise AttributeError(name)
        return getattr(self._method, name)

    @property
    def supports_holdout(self) -> bool:
        return self._method.supports_holdout

    @property
    def stops_itself(self) -> bool:
        return self._method.stops_itself

    @property
    def left_out(self) -> list:
        return self._method.left_out

    @property
    def notes(self) -> list[str]:
        return self._method.notes

    def log_ready(self) -> bool:
        return self._method.log_ready()

    def converged(self) -> str | None:
        return self._method.converged()

    def budget_cut(self) -> str:
        return self._method.budget_cut()

    def components(self) -> dict:
        return self._method.components()

    def resolved_settings(self) -> dict | None:
        return self._method.resolved_settings()

    def end_fit(self) -> None:
        self._method.end_fit()


@dataclass
class LoopSettings:
    # The run's clock (rngcam.recon.loop.Clock): the loop stops at its deadline. None: a clock made
    # when the loop starts, set-up included, with `time_budget_s` (a loop run on its own: tests, bench).
    clock: Clock | None = None
    time_budget_s: float | None = None
    max_iters: int | None = None  # the iteration to stop at (a resumed run counts from its checkpoint's)
    log_every_s: float = 2.0
    log_every_iters: int | None = None
    checkpoint_dir: Path | None = None
    checkpoint_every_s: float = 60.0
    # resume: continue from checkpoint_dir's checkpoint if there is one (without a clock, its wall
    # time counts in the budget). resume_from: continue from this checkpoint payload (the runner's).
    resume: bool = False
    resume_from: dict | None = None
    checkpoint_meta: dict = field(default_factory=dict)  # stored with every checkpoint (its identity)
    stop_requested: Callable[[], str | None] | None = None  # asked after every step: a reason stops the run
    log_line: Callable[[str], None] | None = None  # also gets every plain progress line (a log file)
    max_failures: int = 5
    progress: bool = True
    progress_every_s: float = 10.0  # without a terminal: one progress line this often (stderr)

    def __post_init__(self):
        seconds = self.time_budget_s if self.clock is None else self.clock.seconds
        if seconds is None and self.max_iters is None:
            raise ValueError("set a time budget, an iteration count, or both")
        if self.time_budget_s is not None:
            check_seconds("time_budget_s", self.time_budget_s)
        if self.max_iters is not None and self.max_iters < 0:
            raise ValueError(f"iteration count must be >= 0, got {self.max_iters}")


# A log row comes after at least this many times its own cost in steps, so rows take at most ~5 %
# of a run (a row is a whole video, or four for the fast preset's ensemble: bench/convergence.md, "log rows
# and the refinement's stall window").
LOG_COST_RATIO = 19

# What ended a run (metrics.json's "ended_by"): the method's own stop, the time budget, the
# iteration count, a signal, non-finite steps, or a one-shot method's single pass.
ENDINGS = ("own_stop", "budget", "iterations", "signal", "failure", "one_shot")


@dataclass
class RunResult:
    log: list[dict]
    iterations: int
    solve_s: float
    wall_s: float
    events: list[str] = field(default_factory=list)
    status: str = "ok"  # "ok", "failed", "interrupted" or "budget_before_first_iteration"
    message: str = ""
    ended_by: str = "iterations"  # one of ENDINGS: what ended the run


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


def run(method: Method, settings: LoopSettings,
        evaluate: Callable[[Method], dict[str, float]] | None = None, setup_s: float = 0.0) -> RunResult:
    """Iterate `method` under `settings`; `evaluate(method)` adds truth metrics to each log row.

    `setup_s` is the time the method took to build (operator norms, initialisation): it counts
    as solve time. Logs are spaced so that a row (evaluation, the state's check and copy) costs at
    most ~10 % of the run. A KeyboardInterrupt inside a step (a second Ctrl-C, a notebook's
    interrupt) or a reason from `stop_requested` ends the run "interrupted" with the last good state.
    """
    loop = _Loop(method, settings, evaluate, setup_s)
    with _progress(settings, method.name, loop.clock) as bar:
        loop.bar = bar
        if not loop.log:
            loop.record(float("nan"), show=False)
        while loop.stop is None and not loop.done():
            loop.step()
        return loop.end()


class _Loop:
    """One run of the loop: its state, a step with its checks, and `end`, where how it ended is decided."""

    def __init__(self, method: Method, settings: LoopSettings, evaluate, setup_s: float):
        self.method, self.settings, self.evaluate, self.setup_s = method, settings, evaluate, setup_s
        self.log: list[dict] = []
        self.events: list[str] = []
        self.iteration, self.solve_s = 0, float(setup_s)
        self.ckpt = None if settings.checkpoint_dir is None else Path(settings.checkpoint_dir) / CHECKPOINT_NAME
        wall_offset = self._resume()
        self.first_iteration = self.iteration
        self.clock = settings.clock or Clock(
            time.perf_counter() - wall_offset - (setup_s if not self.log else 0.0), settings.time_budget_s)
        self.last_good = (copy.deepcopy(method.state_dict()), self.iteration, self.solve_s)
        self.failures, self.objective = 0, float("nan")
        self.last_log_solve, self.eval_s, self.last_ckpt_t = -math.inf, 0.0, time.perf_counter()
        self.stop: tuple[str, str] | None = None  # (one of ENDINGS, why): set where the loop must end
        self.bar = None

    def _resume(self) -> float:
        """Load the checkpoint to continue from, if any; the wall time it counts in the budget."""
        settings, saved, wall_offset = self.settings, self.settings.resume_from, 0.0
        if saved is None and settings.resume and self.ckpt is not None and os.path.lexists(self.ckpt):
            saved = checkpoint.load(self.ckpt, hint=RESUME_HINT)  # data only; its identity before its state
            why = checkpoint.mismatch(saved, settings.checkpoint_meta) if settings.checkpoint_meta else ""
            if why:
                raise RngcamError(f"cannot resume from {self.ckpt}: {why}; {RESUME_HINT}")
            wall_offset = saved["wall_s"]  # a sweep's rung: the budget is the fit's total
        if saved is not None and saved.get("method") is not None:
            self.method.load_state_dict(saved["method"])
            self.iteration = saved["iteration"]
            self.solve_s = saved["solve_s"] + (self.setup_s if settings.resume_from else 0.0)
            self.log = saved["log"]
            self.events = [e for e in saved["events"] if not e.startswith("resumed from ")]
            self.events.append(f"resumed from {CHECKPOINT_NAME} at iteration {self.iteration}")
            torch.set_rng_state(saved["rng"])
        return wall_offset

    def wall(self) -> float:
        return self.clock.elapsed()

    def done(self) -> bool:
        if self.settings.max_iters is not None and self.iteration >= self.settings.max_iters:
            return True
        return self.clock.expired()

    def record(self, objective: float, show: bool = True) -> dict:
        t0 = time.perf_counter()
        row = {"iteration": self.iteration, "wall_s": self.wall(), "solve_s": self.solve_s, "objective": objective}
        row.update({f"residual_{k}": v for k, v in self.method.residuals().items()})
        if self.evaluate is not None:
            row.update(self.evaluate(self.method))
        self.log.append(row)
        self.eval_s = time.perf_counter() - t0
        if show and self.bar is not None:
            self.bar.show(row, self.iteration, row["wall_s"])
        return row

    def save_checkpoint(self) -> None:
        if self.ckpt is not None:
            checkpoint.save(self.ckpt, {
                "method": self.method.state_dict(), "iteration": self.iteration, "solve_s": self.solve_s,
                "wall_s": self.wall(), "log": self.log, "events": self.events, "rng": torch.get_rng_state(),
                "identity": self.settings.checkpoint_meta or None})

    def roll_back(self) -> None:
        good, self.iteration, self.solve_s = self.last_good
        self.method.load_state_dict(copy.deepcopy(good))

    def step(self) -> None:
        """One step and its checks: a log row, a checkpoint, a roll-back, or a reason to stop."""
        settings, method = self.settings, self.method
        t0 = time.perf_counter()
        try:
            self.objective = float(method.step())
        except KeyboardInterrupt as exc:  # mid-step: the state may be half updated
            self.roll_back()
            self.stop = ("signal", f"interrupted ({exc or 'KeyboardInterrupt'})")
            self.events.append(f"interrupted by {exc or 'KeyboardInterrupt'} in iteration {self.iteration + 1}: "
                               f"kept the state of iteration {self.iteration}")
            return
        self.solve_s += time.perf_counter() - t0
        self.iteration += 1
        due = (settings.log_every_iters is not None and self.iteration % settings.log_every_iters == 0) or (
            settings.log_every_iters is None
            and self.solve_s - self.last_log_solve >= max(settings.log_every_s, LOG_COST_RATIO * self.eval_s)
            and method.log_ready())
        ckpt_due = self.ckpt is not None and time.perf_counter() - self.last_ckpt_t >= settings.checkpoint_every_s
        asked = settings.stop_requested() if settings.stop_requested is not None else None
        # A non-finite state shows in the next objective; the whole state is checked only where it
        # is kept (log snapshot, checkpoint, the end), not after every step.
        bad, state = not math.isfinite(self.objective), None
        own = method.converged() if not bad and method.stops_itself else None
        t_kept = time.perf_counter()
        if not bad and (due or ckpt_due or self.done() or own or asked):
            state = method.state_dict()
            bad = not _finite_state(state)
        if bad:
            self._failed_step()
            if asked is None or self.stop is not None:
                return
        else:
            self.failures = 0
            if due:
                self.last_log_solve = self.solve_s
                self.record(self.objective)
                self.last_good = (copy.deepcopy(state), self.iteration, self.solve_s)
                self.eval_s = time.perf_counter() - t_kept  # a row's whole cost: the state's check and copy too
            if ckpt_due:
                self.save_checkpoint()
                self.last_ckpt_t = time.perf_counter()
            if own:
                self.stop = ("own_stop", own)
        if asked:
            self.stop = ("signal", asked)
            self.events.append(f"{asked} at iteration {self.iteration}: the state there is written "
                               "(--resume continues)")

    def _failed_step(self) -> None:
        self.failures += 1
        self.roll_back()
        self.method.reduce_step(0.5)
        self.events.append(f"non-finite state at iteration {self.iteration + 1}: rolled back, step halved "
                           f"(failure {self.failures} of {self.settings.max_failures})")
        if self.failures >= self.settings.max_failures:
            self.stop = ("failure", f"{self.failures} non-finite steps in a row; kept the last good state "
                                    f"(iteration {self.iteration})")

    def end(self) -> RunResult:
        """How the run ended (ended_by, status, message), decided here only; the last row and checkpoint."""
        name, (kind, why) = self.method.name, self.stop or ("", "")
        status, message = "ok", ""
        if kind == "failure":
            ended_by, status, message = "failure", "failed", f"{name}: {why}"
        elif kind == "signal":
            ended_by, status, message = "signal", "interrupted", f"{name}: {why}"
        elif kind == "own_stop":
            ended_by = "own_stop"
            self.events.append(f"stopped at iteration {self.iteration}: {why}")
        elif self.clock.expired() and (self.settings.max_iters is None or self.iteration < self.settings.max_iters):
            ended_by = "budget"
            self.events.append(budget_event(self.method, self.clock.seconds, self.iteration, self.setup_s))
            if self.iteration == self.first_iteration:
                status, message = "budget_before_first_iteration", f"{name}: the time budget ran out before the " \
                                                                    "first iteration"
        else:
            ended_by = "iterations"
        if kind == "failure" or not self.log or self.log[-1]["iteration"] != self.iteration:
            self.record(float("nan") if kind == "failure" else self.objective)
        self.save_checkpoint()
        return RunResult(self.log, self.iteration, self.solve_s, self.wall(), self.events, status, message, ended_by)


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


def stage_printer(echo=None, enabled: bool = True, check: Callable[[], None] | None = None):
    """A callable `stage(message)` that prints 'set-up: message (t s)' with the time since it was made,
    so every set-up stage shows progress in a terminal and in a log alike; `check()` runs first (it
    raises what ends the set-up: rngcam.recon.phases)."""
    t0 = time.perf_counter()
    echo = echo or (lambda line: print(line, file=sys.stderr, flush=True))

    def stage(message: str) -> None:
        if check is not None:
            check()
        if enabled:
            echo(f"set-up: {message} ({time.perf_counter() - t0:.1f} s)")
    return stage


class _progress:
    """A rich progress bar showing the latest figures in a terminal; without one, a plain line
    every `progress_every_s` seconds on stderr (so a log file shows the run as it goes); silent
    when progress=False."""

    def __init__(self, settings: LoopSettings, name: str, clock: Clock):
        self.settings, self.name, self._bar, self._task = settings, name, None, None
        self.budget_s = clock.seconds
        self._lines = settings.progress and not is_terminal()
        self._last_line = -math.inf

    def __enter__(self):
        if self.settings.progress and not self._lines:
            self._bar = Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                                 TextColumn("{task.fields[figures]}"), transient=False)
            total = self.budget_s or self.settings.max_iters
            self._task = self._bar.add_task(self.name, total=total, figures="")
            self._bar.start()
        return self

    def show(self, row: dict, iteration: int, wall_s: float) -> None:
        # the data residuals (relative, of every measurement) say how well the fit explains the
        # cameras; the objective of one step is a noisy estimate from a sample of RS rows
        res = "  ".join(f"{k[9:].upper()} residual {v:.4f}" for k, v in row.items()
                        if k.startswith("residual_") and v == v)
        figs = f"iteration {iteration}  " + (res or f"objective {row['objective']:.4g}")
        if "psnr_db" in row:
            figs += f"  PSNR {row['psnr_db']:.2f} dB"
        log_line = self.settings.log_line
        if (self._lines or log_line) and wall_s - self._last_line >= self.settings.progress_every_s:
            self._last_line = wall_s
            budget = f" of {self.budget_s:g} s" if self.budget_s else ""
            line = f"{self.name}: {wall_s:.0f} s{budget}  {figs}"
            if log_line:
                log_line(line)
            if self._lines:
                print(line, file=sys.stderr, flush=True)
        if self._lines:
            return
        if self._bar is None:
            return
        done = wall_s if self.budget_s else iteration
        self._bar.update(self._task, completed=done, figures=figs)

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.stop()
        return False
