"""Run one reconstruction with any method: the one place every caller goes through.

`solve(source, settings, out)` takes a bundle (on disk or read) or a Problem, runs the method
of `settings` (rngcam.recon.registry) and returns a `Result` (rngcam.recon.result); with `out`
it also checkpoints there and writes every output (recon.h5, video.tif, preview.mp4,
errors.csv/png, metrics.json, and recon.log: every line it printed). Iterative methods (stfm,
tv3d, pnp) go through the shared loop; GS-only baselines (blend, interp, rife) are one shot and
give a single point of error against time. The bundle is only read, and the truth never
reaches a method (`method_view`).

The time budget counts from the start: reading, set-up and solve. Set-up is cut where the budget
ends (rngcam.recon.guard), the result then being the start video with status
"budget_before_first_iteration"; SIGINT or SIGTERM end the run "interrupted" with the current
estimate and a checkpoint. `resume` continues a checkpoint of the same bundle, method and
settings (rngcam.recon.checkpoint), with a budget of its own.

With `holdout` set (a fraction of RS row bins; `holdout_gs`, a fraction of GS pixels, is 0 by
default), iterative methods fit only a seeded training split of the measurements
(Problem.with_holdout) and every log row, errors.csv and metrics.json carry the
relative residual on the held-out part (`heldout_rs`, `heldout_gs`, `heldout`; see
rngcam.recon.holdout) next to the training residuals.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from rngcam.cpu import choose_threads, torch_threads
from rngcam.errors import RngcamError, SettingError
from rngcam.formats.bundle import Bundle, bundle_checksum, is_warning, open_checked
from rngcam.memory import peak_rss_bytes, release_free_memory
from rngcam.physics.operators import drop_scratch
from rngcam.recon import checkpoint, outputs, registry
from rngcam.recon.guard import BudgetCut, RunGuard
from rngcam.recon.loop import LoopSettings, RunResult, run, stage_printer
from rngcam.recon.metrics import (
    error_visibility,
    error_visibility_caveats,
    gs_forward,
    motion_metrics,
    one_object_scene,
    relative_residual,
    video_metrics,
)
from rngcam.recon.problem import Problem, build_problem
from rngcam.recon.result import Result
from rngcam.recon.runlog import RunLog
from rngcam.recon.settings import (  # noqa: F401 - their home before settings.py; callers import them here
    AUTO_MAX_S,
    ReconSettings,
    auto_time_budget,
    check_device,
    check_settings_figures,
    default_out_dir,
    resolve_device,
)
from rngcam.sizing import check_size, gib, plan_grid

# Above this many video elements, the log rows during a run carry PSNR only and the final row also
# SSIM, which is most of a truth evaluation's cost (bench/scale.md).
SSIM_EVERY_ROW_MAX_ELEMENTS = 20_000_000

# Of a time budget, this fraction (at most FINISH_MAX_S) is kept for what follows the solve (the
# final metrics, recon.h5, the TIFF, MP4 and plots), so a whole run ends near its budget.
FINISH_FRACTION = 0.1
FINISH_MAX_S = 60.0


def method_view(problem: Problem) -> Problem:
    """What a method may see of `problem`: everything but the truth (the one place it is stripped)."""
    return replace(problem, truth=None)


def make_method(problem: Problem, settings: ReconSettings, device: str, stage=None, budget_s: float | None = None):
    """The iterative method of `settings` on `problem` (float32 on `device`, without the truth);
    `stage(message)` reports set-up stages; `budget_s` is what is left of the budget [all of it]."""
    entry = registry.get(settings.method)
    seen = method_view(problem)  # a float32 copy is 4 bytes a voxel
    method = entry.factory(seen.to(torch.float32, device), settings.method_settings, device=device,
                           budget_s=settings.time_budget_s if budget_s is None else budget_s, stage=stage)
    if problem.has_holdout and not method.supports_holdout:
        raise SettingError(f"{settings.method} does not fit a held-out split yet (holdout)", "holdout")
    return method


def gs_key_frames(problem: Problem) -> np.ndarray:
    """The GS frames as intensities (C, G, H, W): each divided by its exposure in frames."""
    return problem.gs_images().cpu().float().numpy()


def run_gs_only(problem: Problem, settings: ReconSettings) -> tuple[registry.GSOnlyVideo, RunResult]:
    """The GS-only method of `settings` on `problem`'s key frames, and its one-point run."""
    if problem.b_gs is None or problem.b_gs.shape[1] == 0:
        gone = [m for m, _ in problem.left_out if m.startswith("GS")]
        why = f"every GS frame was left out ({', '.join(gone)})" if gone else "the bundle has none"
        raise SettingError(f"method {settings.method} needs GS frames; {why}", "method")
    key = gs_key_frames(problem)
    t0 = time.perf_counter()
    out = registry.get(settings.method).factory(key, problem.gs_times_s, problem.frame_times_s,
                                                settings.method_settings)
    secs = time.perf_counter() - t0
    out.video = np.asarray(out.video, np.float32)
    return out, RunResult(log=[], iterations=1, solve_s=secs, wall_s=secs, ended_by="one_shot")


def start_video(problem: Problem) -> np.ndarray:
    """The video a run that never iterated reports: the GS key frames cross-faded, else zeros."""
    if problem.b_gs is not None and problem.b_gs.shape[1]:
        from rngcam.recon.methods.baselines import blend

        return np.asarray(blend(gs_key_frames(problem), problem.gs_times_s, problem.frame_times_s), np.float32)
    return np.zeros(problem.shape, np.float32)


def _residuals(problem: Problem, video: torch.Tensor) -> dict[str, float]:
    """Relative RS and GS residuals of `video`, computed in float64 a chunk of frames at a time."""
    out = {}
    if problem.b_rs is not None:
        out["rs"] = relative_residual(problem.rs_op().A(video, dtype=torch.float64), problem.b_rs)
    if problem.b_gs is not None and problem.b_gs.shape[1]:
        out["gs"] = relative_residual(gs_forward(problem.gs_op(), video), problem.b_gs)
    return out


def _out_of_memory(exc: BaseException) -> bool:
    text = str(exc).lower()
    return isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and (
        "can't allocate memory" in text or "out of memory" in text or "not enough memory" in text))


@dataclass
class Source:
    """What a run reconstructs: a bundle (read, or a `path` to read) or a ready Problem."""

    path: Path | None = None
    bundle: Bundle | None = None
    problem: Problem | None = None
    warnings: tuple[str, ...] = ()
    sha256: str | None = None

    @property
    def name(self) -> str:
        return self.path.name if self.path is not None else "the bundle" if self.bundle else "the problem"

    def checksum(self) -> str:
        """The bundle file's sha256 ('' for a Problem given directly), computed once."""
        if self.sha256 is None:
            self.sha256 = bundle_checksum(self.path) if self.path is not None else ""
        return self.sha256


def solve(source: Source, settings: ReconSettings, out: Path | None = None,
          echo: Callable[[str], None] | None = print, started: float | None = None) -> Result:
    """Reconstruct `source` under `settings`; with `out`, checkpoint there and write every output.
    The budget counts from `started` (a time.perf_counter(); None: now).

    The folder is checked first (rngcam.recon.checkpoint.prepare: nothing is touched on a
    refusal); the video's frame count and memory are checked against the limits before anything
    frame-sized is allocated; running out of memory anyway is one RngcamError line.
    """
    echo = echo or (lambda _line: None)
    try:
        return _solve(source, settings, Path(out) if out is not None else None, echo, started)
    except (MemoryError, RuntimeError) as exc:
        if not _out_of_memory(exc):
            raise
        raise SettingError(f"{settings.method} ran out of memory on {source.name} ({type(exc).__name__}); "
                           f"use a coarser grid_bin or free memory", "grid_bin") from None


def reconstruct(bundle_path: str | Path, out_dir: str | Path | None = None,
                settings: ReconSettings | None = None, echo=print) -> dict:
    """Reconstruct the bundle at `bundle_path` into `out_dir` [default_out_dir]; returns the metrics
    written to metrics.json. A failed run (non-finite steps) raises RngcamError after writing."""
    settings = settings or ReconSettings()
    bundle_path = Path(bundle_path)
    out = Path(out_dir) if out_dir is not None else default_out_dir(bundle_path, settings.method)
    result = solve(Source(path=bundle_path), settings, out, echo)
    if result.status == "failed":
        raise RngcamError(f"{result.message}; outputs from the last good state are in {out}")
    return result.metrics


def _solve(source: Source, settings: ReconSettings, out: Path | None, echo, started: float | None) -> Result:
    t_start = time.perf_counter() if started is None else started  # the budget bounds the whole run
    entry = registry.get(settings.method)
    want = saved = None
    if out is not None:
        want = checkpoint.identity(source.checksum(), settings.method, settings.fitted())
        inputs = (source.path,) if source.path else ()
        saved = checkpoint.prepare(out, want, settings.resume, settings.overwrite, inputs=inputs)
    log = RunLog()

    def say(line: str) -> None:
        echo(line)
        log.write(line)

    stage_line = say if settings.progress else log.write
    threads, why = choose_threads(settings.threads)  # before reading: this process is idle meanwhile
    if why:
        say(why)
    try:
        with RunGuard() as guard, torch_threads(threads):
            stage = stage_printer(stage_line, check=guard.check)
            if saved is not None:
                say(f"resuming {out / checkpoint.CHECKPOINT_NAME} (iteration {saved.get('iteration', 0)})")
            elif settings.resume:
                say(f"nothing to resume in {out} (no checkpoint yet): a new run")
            problem, extra = _read(source, settings, say, stage)
            log.open(out)
            budget = None if settings.time_budget_s is None else float(settings.time_budget_s)
            if settings.budget_auto and entry.iterative:
                budget, why = auto_time_budget(settings.method, problem.shape)
                say(why)
            elif settings.budget_auto:  # a one-shot method runs to its end unless given a budget
                budget = None
            if budget is not None:  # set-up and solve stop early enough for the metrics and outputs
                keep = min(FINISH_FRACTION * budget, FINISH_MAX_S)
                stage_line(f"time budget {budget:g} s: {budget - keep:.1f} s for set-up and solve, "
                           f"{keep:.1f} s kept for the metrics and outputs")
                budget -= keep
            guard.set_deadline(None if budget is None else t_start + budget)
            run_out = _fit(problem, settings, extra, budget, guard, stage, say, log, t_start, out, want, saved)
            guard.enter("finish")
            result = _finish(source, problem, settings, extra, run_out, out, want, saved, say)
            result.lines = [line.rstrip("\n") for line in log.held]  # empty where recon.log has them
            return result
    finally:
        log.close()


@contextlib.contextmanager
def _opened(source: Source):
    """(bundle, its warnings): the one already read, or the file opened lazily, so that frames and
    truth stay on disk until the size check has passed and then are read one at a time."""
    if source.bundle is not None:
        yield source.bundle, []
        return
    with open_checked(source.path) as (bundle, problems, _stats):
        yield bundle, [p for p in problems if is_warning(p)]


def _read(source: Source, settings: ReconSettings, say, stage) -> tuple[Problem, dict]:
    """The problem on the grid of `settings` (the bundle read and checked first), and what the
    metrics need of the bundle."""
    problem, warnings = source.problem, list(source.warnings)
    extra: dict = {"one_object": False, "need": None}
    if problem is None:
        with _opened(source) as (bundle, read_warnings):
            warnings += read_warnings
            for warning in warnings:
                say(warning)
            stage(f"read {source.name}")
            plan = plan_grid(bundle, settings.grid_bin)
            extra["need"] = check_size(plan, settings.method, registry.get(settings.method).memory,
                                       max_frames=settings.max_frames, max_memory_bytes=settings.max_memory_bytes)
            problem = build_problem(bundle, grid_bin=settings.grid_bin, max_frames=settings.max_frames)
            extra["one_object"] = one_object_scene(bundle.rig_yaml)  # for the motion yardstick
            extra["context"] = outputs.recon_context(source.path, bundle, problem)  # what the outputs record of it
        stage("measurements binned onto the grid")
    extra["warnings"] = warnings
    if settings.holdout is not None:
        problem = problem.with_holdout(settings.holdout, settings.holdout_gs, settings.holdout_seed)
    for note in problem.notes:
        say(f"note: {note}")
    for what, why in problem.left_out:
        say(f"left out: {what} ({why})")
    return problem, extra


HEARTBEAT_S = 10.0  # a set-up stage that says nothing for this long gets a "still setting up" line


@contextlib.contextmanager
def _heartbeat(line: Callable[[str], None], name: str, t_start: float, budget: float | None):
    """While the body runs, a line every HEARTBEAT_S seconds: every set-up shows progress, in a
    terminal and in recon.log, even through a long stage of a method that reports none."""
    done = threading.Event()

    def beat() -> None:
        while not done.wait(HEARTBEAT_S):
            of = f" of the {budget:.0f} s" if budget is not None else ""
            line(f"set-up: {name} still setting up ({time.perf_counter() - t_start:.0f} s{of})")

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _fit(problem: Problem, settings: ReconSettings, extra: dict, budget: float | None, guard: RunGuard, stage,
         say, log, t_start: float, out: Path | None, want: dict | None, saved: dict | None) -> dict:
    """Set up and run the method; what it gave (video, log, status, ...) as a dict for _finish."""
    from rngcam.recon.holdout import HoldoutScorer

    entry = registry.get(settings.method)
    device = resolve_device(settings.device)
    c, k, h, w = problem.shape
    need = f" (about {gib(extra['need'])} estimated)" if extra.get("need") else ""
    say(f"{settings.method}: {k} frames of {h}x{w}x{c} at {1 / problem.grid.dt_s:,.0f} fps on {device}{need}")
    scorer = HoldoutScorer(problem) if settings.holdout is not None else None
    intermediate = problem.intermediate_frames()

    def truth_metrics(video: torch.Tensor, ssim: bool = True) -> dict:
        if problem.truth is None:
            return {}
        return video_metrics(video.detach().cpu(), problem.truth, intermediate, problem.mask,  # float64 per chunk
                             ssim=ssim)

    progress_ssim = problem.truth is not None and problem.truth.numel() <= SSIM_EVERY_ROW_MAX_ELEMENTS

    def one_row(video: np.ndarray, seconds: float, iteration: int) -> list[dict]:
        vt = torch.from_numpy(video)  # float32: the metrics accumulate in float64 chunk by chunk
        row = {"iteration": iteration, "wall_s": time.perf_counter() - t_start, "solve_s": seconds,
               "objective": float("nan")}
        row.update({f"residual_{key}": v for key, v in _residuals(problem, vt).items()})
        return [{**row, **truth_metrics(vt)}]

    fit = {"device": device, "components": {}, "left_out": [], "notes": [], "method_settings": None,
           "events": [], "status": "ok", "message": "", "truth_metrics": truth_metrics}
    try:
        guard.enter("setup")  # raises a signal held while reading
        if not entry.iterative:
            made, result = run_gs_only(problem, settings)
            fit.update(video=made.video, notes=list(made.notes), method_settings=made.resolved,
                       log=one_row(made.video, result.solve_s, 1), iterations=1, solve_s=result.solve_s,
                       wall_s=time.perf_counter() - t_start, ended_by=result.ended_by)
            for note in fit["notes"]:
                say(f"note: {note}")
            return fit
        left = None if budget is None else budget - (time.perf_counter() - t_start)
        with _heartbeat(settings.progress and say or log.write, settings.method, t_start, budget):
            method = make_method(problem, settings, device, stage=stage, budget_s=left)
        release_free_memory()  # what the set-up let go of (coarse levels, learned networks' activations)
        guard.enter("solve")
    except KeyboardInterrupt as exc:  # guard.Interrupted (SIGINT, SIGTERM) or a plain Ctrl-C
        guard.enter("finish")  # the timer off, further signals held: the start video is written whole
        why = f"interrupted by {getattr(exc, 'signame', 'KeyboardInterrupt')} in set-up"
        return _cut(fit, problem, "interrupted", why, one_row, t_start, saved)
    except BudgetCut:
        guard.enter("finish")
        why = (f"time budget of {budget:g} s reached in set-up ({time.perf_counter() - t_start:.1f} s), "
               f"before the first iteration")
        return _cut(fit, problem, "budget_before_first_iteration", why, one_row, t_start, saved)
    setup_s = fit["setup_s"] = time.perf_counter() - t_start
    stage_line = say if settings.progress else log.write
    stage_line(f"set-up: {settings.method} ready ({setup_s:.1f} s)")
    fit["left_out"], fit["notes"] = list(method.left_out), list(method.notes)
    for note in fit["notes"]:
        say(f"note: {note}")
    for comp, why in fit["left_out"]:
        say(f"left out: {comp} ({why})")
    loop = LoopSettings(time_budget_s=budget, max_iters=settings.max_iters, log_every_s=settings.log_every_s,
                        checkpoint_dir=out, checkpoint_every_s=settings.checkpoint_every_s, resume_from=saved,
                        checkpoint_meta=want or {}, start_time=t_start, stop_requested=guard.stop_reason,
                        log_line=log.write, progress=settings.progress)

    def evaluate(m) -> dict:
        release_free_memory(collect=False)  # the steps' freed heap pages go before the metrics' chunks come
        row = scorer(m.estimate().detach()) if scorer is not None else {}
        return {**row, **truth_metrics(m.estimate(), ssim=progress_ssim)}

    result = run(method, loop, evaluate, setup_s=setup_s)
    if problem.truth is not None and result.log and "ssim" not in result.log[-1]:
        result.log[-1].update(truth_metrics(method.estimate()))  # the final row's SSIM, once
    fit.update(video=method.estimate().detach().float().cpu().numpy(), components=method.components(),
               method_settings=method.resolved_settings(), log=result.log, iterations=result.iterations,
               solve_s=result.solve_s, wall_s=result.wall_s, events=result.events, status=result.status,
               message=result.message, ended_by=result.ended_by)
    fit["notes"] += [n for n in method.notes if n not in fit["notes"]]  # what it learns by the end (the floor)
    # The method's state (the solve's peak) goes before the end-of-run metrics and outputs, which
    # then add to a much smaller base (bench/scale.md: whole-process peak).
    del method
    drop_scratch()  # the operators' kept buffers: the finish makes its own
    release_free_memory()
    # this run's events (a resumed run's list goes on from its checkpoint's: metrics.json keeps all)
    now = max((i for i, e in enumerate(result.events) if e.startswith("resumed from ")), default=0)
    for event in result.events[now:]:
        say(f"event: {event}")
    return fit


def _cut(fit: dict, problem: Problem, status: str, why: str, one_row, t_start: float, saved: dict | None) -> dict:
    """A run ended in set-up: the start video as its result (the checkpoint, if one is resumed, is better:
    the folder then keeps what it has)."""
    wall_s = time.perf_counter() - t_start  # when it was cut; the start video and its scores come after
    video = start_video(problem)
    keep = saved is not None and saved.get("method") is not None
    fit.update(video=video, log=one_row(video, 0.0, 0), iterations=0, solve_s=0.0,
               wall_s=wall_s, status=status, message=f"{why}",
               ended_by="signal" if status == "interrupted" else "budget",
               events=[f"{why}: the start video (GS key frames cross-faded) is the result"
                       if not keep else f"{why}: the folder keeps its earlier result and checkpoint"],
               keep_folder=keep, cut=True)
    return fit


def _finish(source: Source, problem: Problem, settings: ReconSettings, extra: dict, fit: dict,
            out: Path | None, want: dict | None, saved: dict | None, say) -> Result:
    """The metrics and the Result; with `out`, its files (and, for a run cut in set-up, a checkpoint
    that `resume` continues)."""
    from rngcam.recon.holdout import HELDOUT_KEYS

    c, k, h, w = problem.shape
    video = fit["video"]
    final = fit["log"][-1] if fit["log"] else {}
    left_out = problem.left_out + fit["left_out"]
    metrics = {
        "method": settings.method,
        "seconds": fit["solve_s"],
        "wall_seconds": fit["wall_s"],
        "setup_seconds": fit.get("setup_s", fit["wall_s"]),  # reading the bundle and the method's set-up
        "iterations": fit["iterations"],
        "peak_rss_bytes": peak_rss_bytes(),  # this process only (VmHWM)
        "frames": k, "height": h, "width": w, "channels": c, "fps": 1 / problem.grid.dt_s,
        "device": fit["device"], "threads": torch.get_num_threads(),
        "status": fit["status"], "ended_by": fit.get("ended_by", "iterations"),
        "left_out": [{"component": a, "reason": b} for a, b in left_out],
        "events": fit["events"],
        "warnings": list(extra["warnings"]),
        "masked_fraction": {name: float(1 - m.mean()) for name, m in
                            (("rs", problem.rs_valid_mask()), ("gs", problem.gs_valid_mask())) if m is not None},
        "notes": fit["notes"],
    }
    if fit["status"] == "budget_before_first_iteration":
        metrics["warnings"].append(f"the time budget ended the run in set-up ({fit['wall_s']:.0f} s), so the result is "
                                   "the start video, not a fit: give a larger time budget (time_budget_s; "
                                   "on the command line --time-budget), or --resume it")
    if fit["message"]:
        metrics["message"] = fit["message"]
    for key in ("psnr_db", "ssim", "psnr_intermediate_db", "ssim_intermediate", "residual_rs", "residual_gs",
                *HELDOUT_KEYS):
        if key in final:
            metrics[key] = final[key]
    if problem.truth is not None:  # is the remaining error visible above each measurement's noise?
        vt = torch.from_numpy(np.asarray(video))
        metrics["error_visibility"] = error_visibility(problem, vt)
        caveats = error_visibility_caveats(problem)
        if caveats:
            metrics["error_visibility_caveats"] = caveats
        metrics.update(motion_metrics(vt, problem.truth, problem.intermediate_frames(),
                                      one_object=extra["one_object"]))
    method_settings = fit["method_settings"] or asdict(settings.method_settings) or None
    if method_settings is not None:
        metrics["method_settings"] = method_settings  # the preset's values filled in
    resolved = {**asdict(settings), "device": fit["device"], "grid_bin": settings.grid_bin}
    if method_settings is not None:
        resolved["method_settings"] = method_settings
    result = Result(video=video, frame_times_s=np.asarray(problem.frame_times_s), metrics=metrics,
                    components=fit["components"], notes=fit["notes"], warnings=list(extra["warnings"]),
                    left_out=left_out, status=fit["status"], log=fit["log"], message=fit["message"],
                    settings=resolved, bundle_sha256=source.checksum(), frame_interval_s=problem.grid.dt_s,
                    context=extra.get("context") or outputs.recon_context(source.path, None, problem))
    if out is not None and not fit.get("keep_folder"):
        result.save(out, echo=say, truth=problem.truth)  # the report need not read the truth again
        if fit.get("cut"):
            checkpoint.save(out / checkpoint.CHECKPOINT_NAME, {
                "method": None, "iteration": 0, "solve_s": 0.0, "wall_s": fit["wall_s"], "log": [],
                "events": [], "rng": torch.get_rng_state(), "identity": want})
    for event in fit["events"] if fit.get("cut") else ():
        say(f"event: {event}")
    return result
