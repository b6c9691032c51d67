"""Run one reconstruction of a bundle with any method and write every output.

Methods come from rngcam.recon.registry. Iterative ones (stfm, tv3d, pnp) go through the shared
loop; GS-only baselines (blend, interp, rife) are one shot and give a single point of error
against time. The bundle is only read.

With `holdout` set (a fraction of RS row bins; `holdout_gs`, a fraction of GS pixels, is 0 by
default), iterative methods fit only a seeded training split of the measurements
(Problem.with_holdout) and every log row, errors.csv and metrics.json carry the
relative residual on the held-out part (`heldout_rs`, `heldout_gs`, `heldout`; see
rngcam.recon.holdout) next to the training residuals.
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rngcam.errors import ConfigError, RngcamError
from rngcam.formats.bundle import bundle_checksum, read_bundle_with_warnings
from rngcam.memory import peak_rss_bytes
from rngcam.recon import outputs, registry
from rngcam.recon.loop import LoopSettings, RunResult, run, stage_printer
from rngcam.recon.metrics import (
    error_visibility,
    error_visibility_caveats,
    motion_metrics,
    one_object_scene,
    relative_residual,
    video_metrics,
)
from rngcam.recon.problem import Problem, build_problem
from rngcam.sizing import check_size, gib, plan_grid

# "auto" scales the registry's budgets (MethodEntry.auto_budget_s, set at 64x64 px, 67 frames, 3
# channels) with the square root of the problem's size, capped at half an hour: 64 px keeps its
# figure, 228x342x232 gets 8.1x it.
AUTO_REFERENCE_VOXELS = 3 * 67 * 64 * 64
AUTO_MAX_S = 1800.0


def auto_time_budget(method: str, shape: tuple[int, int, int, int]) -> tuple[float, str]:
    """The `auto` budget for `method` on a video of `shape` (C, K, H, W), and a line saying why."""
    base = registry.get(method).auto_budget_s
    scale = max(1.0, math.sqrt(math.prod(shape) / AUTO_REFERENCE_VOXELS))
    budget = min(AUTO_MAX_S, base * scale)
    return budget, (f"time budget auto: {budget:.0f} s ({method}'s {base:g} s at 64 px x "
                    f"{scale:.1f} for {math.prod(shape) / 1e6:.1f} M voxels, at most {AUTO_MAX_S:g} s)")


@dataclass
class ReconSettings:
    method: str = "stfm"  # a registry name
    method_settings: Any = None  # an instance of the method's settings dataclass (None: its default preset)
    time_budget_s: float | str | None = "auto"  # "auto": the method's MethodEntry.auto_budget_s, scaled
    max_iters: int | None = None
    device: str = "auto"
    grid_bin: int | None = None
    log_every_s: float = 2.0
    checkpoint_every_s: float = 60.0
    resume: bool = False
    overwrite: bool = False  # write into a non-empty output folder (else refused, unless resuming)
    progress: bool = True
    holdout: float | None = None  # fraction of RS row bins held out of the fit (None: fit everything)
    holdout_gs: float = 0.0  # fraction of GS pixels also held out (with holdout set)
    holdout_seed: int = 0
    max_frames: int | None = None  # refuse a longer video before allocating it (None: sizing's default)
    max_memory_bytes: int | None = None  # refuse a larger estimate (None: a fraction of the machine's)

    def __post_init__(self):
        entry = registry.get(self.method)
        if self.method_settings is None:
            self.method_settings = entry.settings()
        elif not isinstance(self.method_settings, entry.settings_type):
            raise ConfigError(f"{self.method} takes {entry.settings_type.__name__}, "
                              f"not {type(self.method_settings).__name__}")
        self.budget_auto = self.time_budget_s == "auto"  # rescaled to the problem in reconstruct()
        if self.time_budget_s == "auto":
            self.time_budget_s = entry.auto_budget_s
        check_settings_figures(self.time_budget_s, self.max_iters, self.max_frames, self.max_memory_bytes)
        if self.holdout is not None:
            if not 0 < self.holdout < 1:
                raise ConfigError(f"holdout must be a fraction in (0, 1), got {self.holdout}")
            if not entry.iterative:
                fitted = ", ".join(registry.names(registry.ITERATIVE))
                raise ConfigError(f"--holdout applies to fitted methods ({fitted}), not {self.method}")


def check_settings_figures(time_budget_s, max_iters, max_frames=None, max_memory_bytes=None) -> None:
    """ConfigError (one line) for a budget, iteration count or limit that cannot be meant."""
    import math

    if time_budget_s is not None and not (isinstance(time_budget_s, (int, float))
                                          and math.isfinite(time_budget_s) and time_budget_s > 0):
        raise ConfigError(f"--time-budget must be a positive number of seconds, got {time_budget_s!r}")
    for name, value in (("--iters", max_iters), ("--max-frames", max_frames),
                        ("--max-memory", max_memory_bytes)):
        if value is not None and not (isinstance(value, (int, float)) and value >= 1):
            raise ConfigError(f"{name} must be at least 1, got {value!r}")


def resolve_device(name: str) -> str:
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device cuda was asked for but no GPU is available")
    return name


def default_out_dir(bundle_path: Path, method: str) -> Path:
    """A sibling folder of the bundle: <stem>-recon-<method>/."""
    return bundle_path.with_name(f"{bundle_path.stem}-recon-{method}")


def gs_key_frames(problem: Problem) -> np.ndarray:
    """The GS frames as intensities (C, G, H, W): each divided by its exposure in frames."""
    return problem.gs_images().cpu().float().numpy()


def make_method(problem: Problem, settings: ReconSettings, device: str, stage=None):
    """The iterative method of `settings` on `problem` (float32 on `device`); `stage(message)`
    reports set-up stages."""
    entry = registry.get(settings.method)
    problem = replace(problem, truth=None)  # methods never see the truth; a float32 copy is 4 bytes a voxel
    method = entry.factory(problem.to(torch.float32, device), settings.method_settings, device=device,
                           budget_s=settings.time_budget_s, stage=stage)
    if problem.has_holdout and not method.supports_holdout:
        raise ConfigError(f"{settings.method} does not fit a held-out split yet (--holdout)")
    return method


def run_gs_only(problem: Problem, settings: ReconSettings) -> tuple[registry.GSOnlyVideo, RunResult]:
    """The GS-only method of `settings` on `problem`'s key frames, and its one-point run."""
    if problem.b_gs is None or problem.b_gs.shape[1] == 0:
        gone = [m for m, _ in problem.left_out if m.startswith("GS")]
        why = f"every GS frame was left out ({', '.join(gone)})" if gone else "the bundle has none"
        raise RngcamError(f"--method {settings.method} needs GS frames; {why}")
    key = gs_key_frames(problem)
    t0 = time.perf_counter()
    out = registry.get(settings.method).factory(key, problem.gs_times_s, problem.frame_times_s,
                                                settings.method_settings)
    secs = time.perf_counter() - t0
    out.video = np.asarray(out.video, np.float32)
    return out, RunResult(log=[], iterations=1, solve_s=secs, wall_s=secs)


def _residuals(problem: Problem, video: torch.Tensor) -> dict[str, float]:
    out = {}
    if problem.b_rs is not None:
        out["rs"] = relative_residual(problem.rs_op().A(video, frame_chunk=16), problem.b_rs)
    if problem.b_gs is not None and problem.b_gs.shape[1]:
        out["gs"] = relative_residual(problem.gs_op().A(video), problem.b_gs)
    return out


def _out_of_memory(exc: BaseException) -> bool:
    text = str(exc).lower()
    return isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and (
        "can't allocate memory" in text or "out of memory" in text or "not enough memory" in text))


def reconstruct(bundle_path: str | Path, out_dir: str | Path | None = None,
                settings: ReconSettings | None = None, echo=print) -> dict:
    """Reconstruct `bundle_path` into `out_dir`; returns the metrics written to metrics.json.

    The bundle's warnings are echoed first and stored in metrics.json; the video's frame count
    and memory are checked against the limits before anything frame-sized is allocated; running
    out of memory anyway is one RngcamError line.
    """
    settings = settings or ReconSettings()
    bundle_path = Path(bundle_path)
    try:
        return _reconstruct(bundle_path, out_dir, settings, echo)
    except (MemoryError, RuntimeError) as exc:
        if not _out_of_memory(exc):
            raise
        raise RngcamError(f"{settings.method} ran out of memory on {bundle_path.name} "
                          f"({type(exc).__name__}); use a coarser --bin or free memory") from None


def check_out_dir(out: Path, settings: ReconSettings) -> None:
    """Refuse (one line) to write into a non-empty folder unless told to overwrite or resume."""
    if out.exists() and not out.is_dir():
        raise RngcamError(f"output folder {out} is a file")
    if out.is_dir() and any(out.iterdir()) and not (settings.overwrite or settings.resume):
        raise RngcamError(f"output folder {out} is not empty; pass --overwrite to replace what is in it "
                          f"(or --resume to continue from its checkpoint)")


def _reconstruct(bundle_path: Path, out_dir, settings: ReconSettings, echo) -> dict:
    t_start = time.perf_counter()  # the budget bounds reading, set-up and solve together
    out = Path(out_dir) if out_dir is not None else default_out_dir(bundle_path, settings.method)
    check_out_dir(out, settings)
    stage = stage_printer(echo, settings.progress)
    bundle, warnings = read_bundle_with_warnings(bundle_path)
    for warning in warnings:
        echo(warning)
    stage(f"read {bundle_path.name}")
    plan = plan_grid(bundle, settings.grid_bin)
    need = check_size(plan, settings.method, registry.get(settings.method).memory, max_frames=settings.max_frames,
                      max_memory_bytes=settings.max_memory_bytes)
    device = resolve_device(settings.device)
    problem = build_problem(bundle, grid_bin=settings.grid_bin, max_frames=settings.max_frames)
    one_object = one_object_scene(bundle.rig_yaml)  # for the motion yardstick
    del bundle  # the problem holds what the reconstruction needs; the raw frames can go
    stage("measurements binned onto the grid")
    out.mkdir(parents=True, exist_ok=True)
    from rngcam.recon.holdout import HELDOUT_KEYS, HoldoutScorer

    scorer = None
    if settings.holdout is not None:
        problem = problem.with_holdout(settings.holdout, settings.holdout_gs, settings.holdout_seed)
        scorer = HoldoutScorer(problem)
    for note in problem.notes:
        echo(f"note: {note}")
    for what, why in problem.left_out:
        echo(f"left out: {what} ({why})")
    c, k, h, w = problem.shape
    echo(f"{settings.method}: {k} frames of {h}x{w}x{c} at {1 / problem.grid.dt_s:,.0f} fps on {device} "
         f"(about {gib(need)} estimated)")
    entry = registry.get(settings.method)
    if settings.budget_auto and entry.iterative:
        settings.time_budget_s, why = auto_time_budget(settings.method, problem.shape)
        echo(why)
    intermediate = problem.intermediate_frames()

    def truth_metrics(video: torch.Tensor) -> dict:
        if problem.truth is None:
            return {}
        return video_metrics(video.detach().cpu(), problem.truth, intermediate, problem.mask)  # float64 per chunk

    components, left_out, status, message, method_settings = {}, [], "ok", "", None
    notes: list[str] = []  # substitutions a method made (e.g. missing learned weights) and their cost
    if not entry.iterative:
        made, result = run_gs_only(problem, settings)
        video, notes, method_settings = made.video, list(made.notes), made.resolved
        for note in notes:
            echo(f"note: {note}")
        vt = torch.from_numpy(video).double()
        row = {"iteration": 1, "wall_s": result.solve_s, "solve_s": result.solve_s, "objective": float("nan")}
        row.update({f"residual_{k2}": v for k2, v in _residuals(problem, vt).items()})
        row.update(truth_metrics(vt))
        result.log = [row]
    else:
        method = make_method(problem, settings, device, stage=stage)
        setup_s = time.perf_counter() - t_start
        stage(f"{settings.method} ready")
        left_out, notes = list(method.left_out), list(method.notes)
        for note in notes:
            echo(f"note: {note}")
        for comp, why in left_out:
            echo(f"left out: {comp} ({why})")
        loop = LoopSettings(time_budget_s=settings.time_budget_s, max_iters=settings.max_iters,
                            log_every_s=settings.log_every_s, checkpoint_dir=out,
                            checkpoint_every_s=settings.checkpoint_every_s, resume=settings.resume,
                            progress=settings.progress)
        def evaluate(m) -> dict:
            row = scorer(m.estimate().detach()) if scorer is not None else {}
            return {**row, **truth_metrics(m.estimate())}

        result = run(method, loop, evaluate, setup_s=setup_s)
        video = method.estimate().detach().float().cpu().numpy()
        components = method.components()
        method_settings = method.resolved_settings()
        notes += [n for n in method.notes if n not in notes]  # what a method learns by the end (stfm's start floor)
        status, message = result.status, result.message
        # The method's state (the solve's peak) goes before the end-of-run metrics and outputs,
        # which then add to a much smaller base (bench/scale.md: whole-process peak).
        del method
        gc.collect()
        for event in result.events:
            echo(f"event: {event}")

    final = result.log[-1] if result.log else {}
    metrics = {
        "method": settings.method,
        "seconds": result.solve_s,
        "wall_seconds": result.wall_s,
        "iterations": result.iterations,
        "peak_rss_bytes": peak_rss_bytes(),  # this process only (VmHWM)
        "frames": k, "height": h, "width": w, "channels": c, "fps": 1 / problem.grid.dt_s,
        "device": device, "status": status,
        "left_out": [{"component": a, "reason": b} for a, b in problem.left_out + left_out],
        "events": result.events,
        "warnings": list(warnings),
        "masked_fraction": {name: float(1 - m.mean()) for name, m in
                            (("rs", problem.rs_valid_mask()), ("gs", problem.gs_valid_mask())) if m is not None},
        "notes": notes,
    }
    for key in ("psnr_db", "ssim", "psnr_intermediate_db", "ssim_intermediate", "residual_rs", "residual_gs",
                *HELDOUT_KEYS):
        if key in final:
            metrics[key] = final[key]
    if problem.truth is not None:  # is the remaining error visible above each measurement's noise?
        metrics["error_visibility"] = error_visibility(problem, torch.from_numpy(np.asarray(video)))
        caveats = error_visibility_caveats(problem)
        if caveats:
            metrics["error_visibility_caveats"] = caveats
        metrics.update(motion_metrics(torch.from_numpy(np.asarray(video)), problem.truth, intermediate,
                                      one_object=one_object))
    method_settings = method_settings or asdict(settings.method_settings) or None
    if method_settings is not None:
        metrics["method_settings"] = method_settings  # the preset's values filled in
    resolved = {**asdict(settings), "device": device, "grid_bin": settings.grid_bin}
    if method_settings is not None:
        resolved["method_settings"] = method_settings
    outputs.write_recon_h5(out / "recon.h5", video, problem.frame_times_s, resolved,
                           bundle_checksum(bundle_path), components, problem.left_out + left_out)
    outputs.write_tiff(out / "video.tif", video, frame_interval_s=problem.grid.dt_s)
    outputs.write_mp4(out / "preview.mp4", video, capture_fps=1 / problem.grid.dt_s)
    outputs.write_errors(out / "errors.csv", out / "errors.png", result.log, settings.method)
    outputs.write_metrics(out / "metrics.json", metrics)
    if status != "ok":
        raise RngcamError(f"{message}; outputs from the last good state are in {out}")
    return metrics
