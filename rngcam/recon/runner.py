"""Run one reconstruction with any method: the one place every caller goes through.

`solve(source, settings, out)` takes a bundle (on disk or read) or a Problem, runs the method
of `settings` (rngcam.recon.registry) and returns a `Result` (rngcam.recon.result); with `out`
it also checkpoints there and writes every output (recon.h5, video.tif, preview.mp4,
errors.csv/png, metrics.json, recon.log). Iterative methods go through the shared loop; GS-only
baselines are one shot. The bundle is only read; the truth never reaches a method (`method_view`).

The settings are resolved once the problem is read (rngcam.recon.settings.resolve: a frozen
`Run`); the run's one clock starts with the command (`started`). Set-up is cut at its deadline
(rngcam.recon.phases: the start video, "budget_before_first_iteration"); SIGINT or SIGTERM end
the run "interrupted" with the current estimate and a checkpoint that `resume` continues.
With `holdout`, iterative methods fit a seeded training split (Problem.with_holdout) and the
log rows, errors.csv and metrics.json carry the residual on the held-out part (rngcam.recon.holdout).
"""

from __future__ import annotations

import contextlib
import math
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
from rngcam.memory import peak_rss_bytes, release_before, release_free_memory, returned_on_free
from rngcam.physics.operators import drop_scratch
from rngcam.recon import ablation, checkpoint, outputs, registry
from rngcam.recon.holdout import HELDOUT_KEYS, HoldoutScorer
from rngcam.recon.loop import LoopSettings, Method, RunResult, run, stage_printer
from rngcam.recon.methods.baselines import blend
from rngcam.recon.metrics import (
    error_visibility,
    error_visibility_caveats,
    gs_forward,
    motion_metrics,
    one_object_scene,
    relative_residual,
    video_metrics,
)
from rngcam.recon.misfit import above_noise, for_metrics
from rngcam.recon.phases import BudgetCut, RunPhases
from rngcam.recon.problem import Problem, build_problem
from rngcam.recon.result import Fitted, Result, split_results
from rngcam.recon.runlog import RunLog
from rngcam.recon.settings import (  # noqa: F401 - their home before settings.py; callers import them here
    AUTO_MAX_S,
    Clock,
    ReconSettings,
    Run,
    auto_time_budget,
    check_device,
    check_settings_figures,
    default_out_dir,
    resolve,
    resolve_device,
)
from rngcam.video_plan import check_size, gib, plan_grid

# Above this many video elements, the log rows during a run carry PSNR only and the final row also
# SSIM, which is most of a truth evaluation's cost (bench/large_grids.md).
SSIM_EVERY_ROW_MAX_ELEMENTS = 20_000_000


def method_view(problem: Problem, method_settings=None) -> Problem:
    """What a method may see of `problem`, decided in this one place: everything but the truth, and
    without the camera its settings' ablation removes (`no_gs` / `no_rs`: rngcam.recon.ablation)."""
    seen = replace(problem, truth=None)
    return seen if method_settings is None else ablation.for_method(seen, method_settings)


def make_method(problem: Problem, run_: Run, stage=None) -> Method:
    """The iterative method of `run_` on `problem` (float32 on its device, without the truth),
    reading the run's clock; `stage(message)` reports set-up stages."""
    entry = registry.get(run_.method)
    seen = method_view(problem, run_.settings.method_settings)  # a float32 copy is 4 bytes a voxel
    method = entry.factory(seen.to(torch.float32, run_.device), run_.settings.method_settings, device=run_.device,
                           clock=run_.clock, stage=stage)
    if problem.has_holdout and not method.supports_holdout:
        raise SettingError(f"{run_.method} does not fit a held-out split yet (holdout)", "holdout")
    return method


def explain_run(source: Source, settings: ReconSettings, say=lambda line: None) -> list[str]:
    """What `settings`' method would do on the bundle, one line a stage, without fitting (`--explain`)."""
    entry = registry.get(settings.method)
    if entry.explain is None:
        return [f"{settings.method}: one stage (no recipe to explain)"]
    problem, _ = _read(source, settings, say, lambda message: None)
    return entry.explain(method_view(problem, settings.method_settings).to(torch.float32), settings.method_settings)


def fit_checkpointed(problem: Problem, run_: Run, folder: Path, meta: dict,
                     saved: dict | None) -> tuple[torch.Tensor, RunResult]:
    """`run_`'s method on `problem`, iterated with checkpoints in `folder` (identity `meta`), resumed
    from `saved` (a checkpoint payload, or None): a sweep trial's fit, with no outputs. Its estimate
    and how the run went."""
    method = make_method(problem, run_)
    loop = LoopSettings(clock=run_.clock, max_iters=run_.settings.max_iters, log_every_s=run_.settings.log_every_s,
                        checkpoint_dir=folder, checkpoint_every_s=run_.settings.checkpoint_every_s,
                        resume_from=saved, checkpoint_meta=meta, progress=False)
    result = run(method, loop, setup_s=run_.clock.elapsed() - (saved or {}).get("wall_s", 0.0))
    return method.estimate().detach(), result


def gs_key_frames(problem: Problem) -> np.ndarray:
    """The GS frames as intensities (C, G, H, W): each divided by its exposure in frames."""
    return problem.gs_images().cpu().float().numpy()


def run_gs_only(problem: Problem, settings: ReconSettings) -> tuple[registry.GSOnlyVideo, RunResult]:
    """The GS-only method of `settings` on `problem`'s key frames, and its one-point run."""
    if problem.b_gs is None or problem.b_gs.shape[1] == 0:
        raise SettingError(ablation.needs_gs(settings.method, problem.cameras, problem.left_out), "method")
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


@dataclass
class _Job:
    """What a run's stages share besides the problem and the Run: the guard, the set-up stage
    printer, the output lines (`say`: printed and in recon.log; `log`: recon.log only) and the
    folder with its checkpoint identity and the checkpoint resumed."""

    guard: RunPhases
    stage: Callable[[str], None]
    say: Callable[[str], None]
    log: RunLog
    out: Path | None
    want: dict | None
    saved: dict | None

    def quiet(self, progress: bool) -> Callable[[str], None]:
        """Where a progress-only line goes: printed and logged, or (without progress) logged only."""
        return self.say if progress else self.log.write


def _solve(source: Source, settings: ReconSettings, out: Path | None, echo, started: float | None) -> Result:
    clock = Clock(started)  # the run's one clock: the budget bounds the whole run
    want = saved = None
    if out is not None:
        want = checkpoint.identity(source.checksum(), settings.method, settings.fitted())
        inputs = (source.path,) if source.path else ()
        saved = checkpoint.prepare(out, want, settings.resume, settings.overwrite, inputs=inputs)
    log = RunLog()

    def say(line: str) -> None:
        echo(line)
        log.write(line)

    threads, why = choose_threads(settings.threads)  # before reading: this process is idle meanwhile
    if why:
        say(why)
    try:
        with RunPhases(clock) as guard, torch_threads(threads):
            job = _Job(guard, stage_printer(say if settings.progress else log.write, check=guard.check), say, log,
                       out, want, saved)
            if saved is not None:
                say(f"resuming {out / checkpoint.CHECKPOINT_NAME} (iteration {saved.get('iteration', 0)})")
            elif settings.resume:
                say(f"nothing to resume in {out} (no checkpoint yet): a new run")
            problem, extra = _read(source, settings, say, job.stage)
            log.open(out)
            run_ = resolve(settings, problem.shape, clock)
            if run_.budget_s is not None:  # set-up and solve stop early enough for the metrics and outputs
                (say if settings.time_budget_s == "auto" else job.quiet(settings.progress))(
                    f"time budget {run_.budget_s:.0f} s ({run_.budget_how}): {clock.seconds:.1f} s for set-up "
                    f"and solve, {run_.finish_s:.1f} s kept for the metrics and outputs")
            made = _fit(problem, run_, extra, job)
            guard.enter("finish")
            with returned_on_free():  # the metrics' and writers' temporaries do not pile up
                result = _finish(source, problem, run_, extra, made, job)
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
def _heartbeat(line: Callable[[str], None], name: str, clock: Clock):
    """While the body runs, a line every HEARTBEAT_S seconds: every set-up shows progress, in a
    terminal and in recon.log, even through a long stage of a method that reports none."""
    done = threading.Event()

    def beat() -> None:
        while not done.wait(HEARTBEAT_S):
            of = f" of the {clock.seconds:.0f} s" if clock.seconds is not None else ""
            line(f"set-up: {name} still setting up ({clock.elapsed():.0f} s{of})")

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


class _Rows:
    """Log rows of a video on `problem`: its truth metrics (with truth) and a one-point log."""

    def __init__(self, problem: Problem, clock: Clock):
        self.problem, self.clock = problem, clock
        self.intermediate = problem.intermediate_frames()
        self.progress_ssim = problem.truth is not None and problem.truth.numel() <= SSIM_EVERY_ROW_MAX_ELEMENTS

    def truth(self, video: torch.Tensor, ssim: bool = True) -> dict:
        p = self.problem
        if p.truth is None:
            return {}
        return video_metrics(video.detach().cpu(), p.truth, self.intermediate, p.mask, ssim=ssim)  # float64 chunks

    def one(self, video: np.ndarray, seconds: float, iteration: int) -> list[dict]:
        vt = torch.from_numpy(video)  # float32: the metrics accumulate in float64 chunk by chunk
        row = {"iteration": iteration, "wall_s": self.clock.elapsed(), "solve_s": seconds, "objective": float("nan")}
        row.update({f"residual_{key}": v for key, v in _residuals(self.problem, vt).items()})
        return [{**row, **self.truth(vt)}]


def _fit(problem: Problem, run_: Run, extra: dict, job: _Job) -> Fitted:
    """Set up and run the method; what it gave (video, log, status, ...) for _finish."""
    clock, entry = run_.clock, registry.get(run_.method)
    c, k, h, w = problem.shape
    need = f" (about {gib(extra['need'])} estimated)" if extra.get("need") else ""
    job.say(f"{run_.method}: {k} frames of {h}x{w}x{c} at {1 / problem.grid.dt_s:,.0f} fps on {run_.device}{need}")
    rows = _Rows(problem, clock)
    made = Fitted(device=run_.device)
    try:
        job.guard.enter("setup")  # raises a signal held while reading
        if not entry.iterative:
            gs_only, result = run_gs_only(problem, run_.settings)
            made = replace(made, video=gs_only.video, notes=list(gs_only.notes), method_settings=gs_only.resolved,
                           log=rows.one(gs_only.video, result.solve_s, 1), iterations=1, solve_s=result.solve_s,
                           wall_s=clock.elapsed(), ended_by=result.ended_by)
            for note in made.notes:
                job.say(f"note: {note}")
            return made
        with _heartbeat(job.quiet(run_.settings.progress), run_.method, clock):
            method = make_method(problem, run_, stage=job.stage)
        release_free_memory()  # what the set-up let go of (coarse levels, learned networks' activations)
        job.guard.enter("solve")
    except KeyboardInterrupt as exc:  # guard.Interrupted (SIGINT, SIGTERM) or a plain Ctrl-C
        job.guard.enter("finish")  # the timer off, further signals held: the start video is written whole
        why = f"interrupted by {getattr(exc, 'signame', 'KeyboardInterrupt')} in set-up"
        return _cut(made, ablation.for_method(problem, run_.settings.method_settings), "interrupted", why, rows,
                    job.saved)
    except BudgetCut:
        job.guard.enter("finish")
        why = (f"time budget of {clock.seconds:g} s reached in set-up ({clock.elapsed():.1f} s), "
               f"before the first iteration")
        return _cut(made, ablation.for_method(problem, run_.settings.method_settings),
                    "budget_before_first_iteration", why, rows, job.saved)
    return _iterate(problem, run_, method, made, rows, job)


def _iterate(problem: Problem, run_: Run, method: Method, made: Fitted, rows: _Rows, job: _Job) -> Fitted:
    """The loop on the method just built, under the run's clock; `made` with what it gave."""
    settings = run_.settings
    setup_s = made.setup_s = run_.clock.elapsed()
    job.quiet(settings.progress)(f"set-up: {run_.method} ready ({setup_s:.1f} s)")
    made.left_out, made.notes = list(method.left_out), list(method.notes)
    for note in made.notes:
        job.say(f"note: {note}")
    for comp, why in made.left_out:
        job.say(f"left out: {comp} ({why})")
    for line in getattr(method, "recipe", None) or []:  # STFM: each stage, what it did or why it was left out
        job.log.write(f"recipe: {line}")
    loop = LoopSettings(clock=run_.clock, max_iters=settings.max_iters, log_every_s=settings.log_every_s,
                        checkpoint_dir=job.out, checkpoint_every_s=settings.checkpoint_every_s, resume_from=job.saved,
                        checkpoint_meta=job.want or {}, stop_requested=job.guard.stop_reason,
                        log_line=job.log.write, progress=settings.progress)
    scorer = HoldoutScorer(problem) if settings.holdout is not None else None

    def evaluate(m) -> dict:
        release_before(problem.truth.nbytes if problem.truth is not None else 0)  # before the metrics' chunks
        row = scorer(m.estimate().detach()) if scorer is not None else {}
        return {**row, **rows.truth(m.estimate(), ssim=rows.progress_ssim)}

    result = run(method, loop, evaluate, setup_s=setup_s)
    with returned_on_free():  # the last estimate's and the components' temporaries go as they are freed
        if problem.truth is not None and result.log and "ssim" not in result.log[-1]:
            result.log[-1].update(rows.truth(method.estimate()))  # the final row's SSIM, once
        video = method.estimate().detach().float().cpu().numpy()
        method.end_fit()  # the optimiser's buffers and the cached raw video go before the components
        release_free_memory(collect=False)  # their pages too: in the heap, the components' buffers would not reuse them
        made = replace(made, video=video, components=method.components(), method_settings=method.resolved_settings(),
                       log=result.log, iterations=result.iterations, solve_s=result.solve_s, wall_s=result.wall_s,
                       events=result.events, status=result.status, message=result.message,
                       ended_by=result.ended_by)
    made.notes += [n for n in method.notes if n not in made.notes]  # what it learns by the end (the floor)
    # The method's state (the solve's peak) goes before the end-of-run metrics and outputs, which
    # then add to a much smaller base (bench/large_grids.md: whole-process peak).
    del method
    drop_scratch()  # the operators' kept buffers: the finish makes its own
    release_free_memory()
    # this run's events (a resumed run's list goes on from its checkpoint's: metrics.json keeps all)
    now = max((i for i, e in enumerate(result.events) if e.startswith("resumed from ")), default=0)
    for event in result.events[now:]:
        job.say(f"event: {event}")
    return made


def _start_name(problem: Problem) -> str:
    return "GS key frames cross-faded" if problem.b_gs is not None and problem.b_gs.shape[1] else "zeros: no GS frames"


def _cut(made: Fitted, problem: Problem, status: str, why: str, rows: _Rows, saved: dict | None) -> Fitted:
    """A run ended in set-up: the start video as its result (the checkpoint, if one is resumed, is better:
    the folder then keeps what it has). `problem`: what the method may see (an ablation's camera gone)."""
    wall_s = rows.clock.elapsed()  # when it was cut; the start video and its scores come after
    video = start_video(problem)
    keep = saved is not None and saved.get("method") is not None
    return replace(made, video=video, log=rows.one(video, 0.0, 0), iterations=0, solve_s=0.0,
                   wall_s=wall_s, status=status, message=f"{why}",
                   ended_by="signal" if status == "interrupted" else "budget",
                   events=[f"{why}: the start video ({_start_name(problem)}) is the result"
                           if not keep else f"{why}: the folder keeps its earlier result and checkpoint"],
                   keep_folder=keep, cut=True)


def _sensor_components(problem: Problem, components: dict) -> dict:
    """A method's named parts in the sensor's orientation: those of the image's shape turned back."""
    if not problem.transposed:
        return components
    image = tuple(problem.shape[-2:])
    return {name: problem.to_sensor(part) if tuple(getattr(part, "shape", ())[-2:]) == image else part
            for name, part in components.items()}


def _finish(source: Source, problem: Problem, run_: Run, extra: dict, fit: Fitted, job: _Job) -> Result:
    """The metrics and the Result; with `job.out`, its files (and, for a run cut in set-up, a checkpoint
    that `resume` continues). The settings as they ran (`Run.record`: recon.h5, metrics.json's
    "settings", the report) are kept apart from what the run found (metrics.json's "method_results")."""
    settings, out = run_.settings, job.out
    c, k, h, w = problem.shape
    if problem.transposed:  # the outputs are in the sensor's orientation (Problem.to_sensor)
        h, w = w, h
    video = fit.video
    final = fit.log[-1] if fit.log else {}
    left_out = problem.left_out + fit.left_out
    metrics = {
        "method": settings.method,
        "seconds": fit.solve_s,
        "wall_seconds": fit.wall_s,
        "setup_seconds": fit.wall_s if fit.setup_s is None else fit.setup_s,  # reading the bundle and the set-up
        "iterations": fit.iterations,
        "peak_rss_bytes": peak_rss_bytes(),  # this process only (VmHWM)
        "frames": k, "height": h, "width": w, "channels": c, "fps": 1 / problem.grid.dt_s,
        "device": fit.device, "threads": torch.get_num_threads(),
        "status": fit.status, "ended_by": fit.ended_by,
        "left_out": [{"component": a, "reason": b} for a, b in left_out],
        "events": fit.events,
        "warnings": list(extra["warnings"]),
        "masked_fraction": {name: float(1 - m.mean()) for name, m in
                            (("rs", problem.rs_valid_mask()), ("gs", problem.gs_valid_mask())) if m is not None},
        "notes": fit.notes,
    }
    if fit.status == "budget_before_first_iteration":
        metrics["warnings"].append(f"the time budget ended the run in set-up ({fit.wall_s:.0f} s), so the result is "
                                   "the start video, not a fit: give a larger time budget (time_budget_s; "
                                   "on the command line --time-budget), or --resume it")
    if fit.message:
        metrics["message"] = fit.message
    for key in ("psnr_db", "ssim", "psnr_intermediate_db", "ssim_intermediate", "residual_rs", "residual_gs",
                *HELDOUT_KEYS):
        if key in final:
            metrics[key] = final[key]
    if problem.truth is not None:  # is the remaining error visible above each measurement's noise?
        vt = torch.from_numpy(np.asarray(video))
        # a sensor whose data cannot vouch (nan) is left out: the caveats below say why, and no NaN is written
        metrics["error_visibility"] = {k: v for k, v in error_visibility(problem, vt).items() if not math.isnan(v)}
        caveats = error_visibility_caveats(problem)
        if caveats:
            metrics["error_visibility_caveats"] = caveats
        metrics.update(motion_metrics(vt, problem.truth, problem.intermediate_frames(),
                                      one_object=extra["one_object"]))
    method_settings, method_results = split_results(fit.method_settings or asdict(settings.method_settings))
    resolved = run_.record()
    if method_settings is not None:
        metrics["method_settings"] = resolved["method_settings"] = method_settings  # the preset's values filled in
    if method_results:
        metrics["method_results"] = method_results
    misfit = for_metrics(metrics)  # the RS residual clearly above the noise level: said, with its likely causes
    if misfit:
        metrics["misfit"] = misfit
    above = above_noise(metrics)  # stopped above the noise level, no verdict: said too
    if above:
        metrics["above_noise"] = above
    metrics["settings"] = {k: v for k, v in resolved.items() if k != "method_settings"}  # that one is above
    release_free_memory(collect=False)  # the metrics' freed heap pages go before the outputs are written
    video = np.ascontiguousarray(problem.to_sensor(video))
    result = Result(video=video, frame_times_s=np.asarray(problem.frame_times_s), metrics=metrics,
                    components=_sensor_components(problem, fit.components), notes=fit.notes,
                    warnings=list(extra["warnings"]),
                    left_out=left_out, status=fit.status, log=fit.log, message=fit.message,
                    settings=resolved, bundle_sha256=source.checksum(), frame_interval_s=problem.grid.dt_s,
                    context=extra.get("context") or outputs.recon_context(source.path, None, problem))
    if out is not None and not fit.keep_folder:
        # the truth here: the report need not read it again
        result.save(out, echo=job.say, truth=problem.to_sensor(problem.truth))
        if fit.cut:
            checkpoint.save(out / checkpoint.CHECKPOINT_NAME, {
                "method": None, "iteration": 0, "solve_s": 0.0, "wall_s": fit.wall_s, "log": [],
                "events": [], "rng": torch.get_rng_state(), "identity": job.want})
    for event in fit.events if fit.cut else ():
        job.say(f"event: {event}")
    return result
