"""The STFM method: one fit (settings resolved, optimiser, steps, outputs, checkpoints)."""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import asdict

import numpy as np
import torch
from torch import Tensor, nn

from rngcam.errors import ConfigError
from rngcam.memory import heap_reuse, release_before
from rngcam.recon import ablation
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.selfcal import describe, pose_matrix, report_lines, similarity
from rngcam.recon.methods.stfm.bases import BaseVideos
from rngcam.recon.methods.stfm.components import Components, choose_components
from rngcam.recon.methods.stfm.fields import transfer_fields
from rngcam.recon.methods.stfm.init import GSInit
from rngcam.recon.methods.stfm.line_time import LineTime, line_time_lines
from rngcam.recon.methods.stfm.loss import DataLoss
from rngcam.recon.methods.stfm.model import FieldModel, _chunks
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.methods.stfm.settings import (
    _FROM_PRESET,
    STFMSettings,
    chunk_frames,
    resolve,
)
from rngcam.recon.methods.stfm.stage_configs import fit_config
from rngcam.recon.methods.stfm.stopping import NoiseStop
from rngcam.recon.metrics import relative_residual
from rngcam.recon.noise import relative_noise_level


def held_schedule(hold_steps: int, ratio: float, after_hold: float) -> dict:
    """An optimiser group's schedule: held (no step) for `hold_steps`, then stepped at `ratio` x
    `after_hold` of the fields' learning rate (the fields' step has decayed meanwhile); `ratio` without
    a hold."""
    return {"hold_steps": hold_steps, "lr_ratio": ratio * (after_hold if hold_steps else 1.0)}


class STFM(FieldModel, LineTime, BaseVideos, DataLoss, GSInit, NoiseStop, MethodBase):
    """STFM as a `rngcam.recon.loop.Method`. Build it with `make_stfm`. Its parts live in the
    package's modules (fields and frames, bases, loss, initialisation, stop test)."""

    name = "stfm"
    stops_itself = True  # NoiseStop.converged
    supports_holdout = True  # fits only the training measurements when the problem has a split

    def __init__(self, problem, settings: STFMSettings, device="cpu", static_from: STFM | None = None,
                 base_video: Tensor | None = None, fields_from: STFM | None = None,
                 rs_norm_start: Tensor | None = None, base_gains: Tensor | None = None,
                 state: RunState | None = None):
        """`static_from`: an STFM of the same problem and preset whose initialised static field
        this one copies instead of fitting it again (ensemble members share that start).
        `base_video` (C, K, H, W), without GS gains: the base of a "video" dynamic base, instead
        of RIFE's or the flow interpolation's (the ensemble's refinement fit); kept as given (half
        precision too: frames are cast as they are sampled), not copied. `base_gains` (C,): the
        base is `base_video` divided by these, on the fly (no divided copy).
        `fields_from`: an STFM of the same model on a coarser grid whose fields (planes resampled)
        and gains this one starts from instead of initialising from the GS frames (coarse to fine).
        `rs_norm_start`: a start for the RS operator's power iteration (a coarser level's
        `rs_norm_vector`, upsampled); given one, the fit keeps its last iterate in `rs_norm_vector`
        for the next level (a video-sized buffer the caller frees), else `rs_norm_vector` is None.
        `state`: what the build found (the preset's choice, self-calibration) and what a later fit is
        made from (rngcam.recon.methods.stfm.run_state); a finer level takes `fields_from`'s."""
        self.settings = settings
        self.state = state or (fields_from.state if fields_from is not None else RunState())
        self.fit_config = fit_config(settings)  # the fit stage's schedule for what it learns of the rig
        choice = self.state.preset_choice  # preset "auto" (the recipe's auto_preset stage): what it chose and why
        self._notes = [f"preset auto chose {choice['preset']}: {choice['reason']}"] if choice else []
        self._notes += report_lines(self.state.selfcal_report)  # the end values: resolved_settings
        self._notes += ablation.selfcal_note(settings)  # --no-gs / --no-rs: nothing to calibrate against
        self._static_from = static_from
        self._given_base = base_video
        self.base_gains = None if base_gains is None else base_gains.to(device, torch.float32)
        self._rs_norm_start, self.rs_norm_vector = rs_norm_start, None
        self.device = torch.device(device)
        self.problem = problem.to(torch.float32, self.device)
        p = self.problem
        p.check_finite("stfm")
        self.C, self.K, self.H, self.W = p.shape
        self.resolved, preset = resolve(settings, self.H, self.W, self.K)
        self.frame_chunk = chunk_frames(settings, self.H, self.W, str(self.device))
        self.parts: Components = choose_components(
            problem, auto=settings.components == "auto", no_static=settings.no_static,
            no_motion_reg=settings.no_motion_reg, no_rs=settings.no_rs, no_gs=settings.no_gs, tau=self.resolved.tau)
        if "," in self.resolved.dynamic_base or self.resolved.dynamic_base == "ensemble":
            raise ConfigError(f"dynamic_base {self.resolved.dynamic_base!r} is an ensemble: build it with make_stfm")
        torch.manual_seed(settings.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(settings.seed)
        self._build_geometry()
        self._build_line_time()
        self._build_base()
        self._build_fields(preset)
        self._build_scales()
        if fields_from is not None:
            transfer_fields(self.fields, fields_from.fields)
            with torch.no_grad():
                self.log_gain.copy_(fields_from.log_gain.detach().to(self.log_gain))
                self.gs_pose.copy_(fields_from.gs_pose.detach().to(self.gs_pose) * (self.W / fields_from.W))
                if fields_from.rs_timing is not None:
                    self.line_shift.copy_(fields_from.line_shift.detach().to(self.line_shift)
                                          * (self.readout_frames / fields_from.readout_frames))
            self._pose_inherited = True
        elif self.resolved.init == "gs" and self.parts.gs:
            self._init_from_gs()
        self.steps = 0
        self._build_optimiser(preset)
        self._params = [*self.fields.parameters(), self.log_gain, self.line_shift, self.gs_pose]
        self._ema = [q.detach().clone() for q in self._params] if self.resolved.ema_decay > 0 else None
        self._cache: tuple[int, Tensor] | None = None
        self._rs_history: dict[int, float] = {}  # step -> relative RS residual at the stop checks
        self.rs_noise_level = (relative_noise_level(self.problem.b_rs.index_select(1, self.rs_rows_fit.to(self.device)))
                               if self.parts.rs else None)

    # ------------------------------------------------------------------ setup

    @property
    def notes(self) -> list[str]:
        return self._notes + learned_notes(self)

    @property
    def left_out(self) -> list[tuple[str, str]]:
        """Components left out and substitutes used (e.g. no RIFE weights), each with why."""
        return list(self.parts.left_out) + list(self.substitutes)


    def _build_optimiser(self, preset: dict) -> None:
        lr = self.resolved.lr
        planes, decoders = [], []
        for module in self.fields.values():
            for pname, param in module.named_parameters():
                (planes if pname.startswith("planes") else decoders).append(param)
        groups = [{"params": planes, "lr_ratio": 1.0}] if planes else []
        if decoders:
            ratio = preset["decoder_lr_ratio"] if planes else 1.0
            groups.append({"params": decoders, "lr_ratio": ratio})
        self.learn_gain = self.parts.rs and self.parts.gs
        if self.learn_gain:
            groups.append({"params": [self.log_gain], "lr_ratio": preset["gain_lr_ratio"]})
        mode = self.settings.learn_geometry
        self.learn_pose = self.learn_gain and mode != "off" and self.settings.gs_anchor == "soft"
        if mode == "shift":  # rotation and scale held at zero (no gradient reaches them)
            self.pose_free[2:] = 0
            self.pose_is_shift = True
        if self.learn_pose:
            groups.append({"params": [self.gs_pose], **self._pose_schedule()})
        self.learn_line = self._line_time_wanted() and self.learn_gain and self.settings.gs_anchor == "soft"
        if self.learn_line:
            groups.append({"params": [self.line_shift], **self._line_schedule()})
        for g in groups:
            g["lr"] = lr * self._ratio(g)
        # fused: one kernel for all parameters (CPU and CUDA), a fraction of the loop's time a step on a CPU
        # (bench/convergence.md, "a fifth off the prior preset's step")
        self.optimiser = torch.optim.Adam(groups, lr=lr, fused=self.device.type in ("cpu", "cuda"))
        self.base_lr = lr

    def _pose_schedule(self) -> dict:
        """The pose group's hold and step: a fit that learns the pose from its start holds it while its
        fields settle, then steps it faster; one started from another fit's pose neither."""
        f = self.fit_config
        return held_schedule(0 if self._pose_inherited else f.pose_hold_steps, f.pose_lr_ratio, f.pose_lr_after_hold)

    def _line_schedule(self) -> dict:
        """The line-time group's hold and step: held while a search-started fit's fields settle, then
        stepped faster (the fields' step has decayed meanwhile); neither in other fits."""
        return held_schedule(self._line_hold(), self.fit_config.line_lr_ratio, self.fit_config.line_lr_after_hold)

    def _line_hold(self) -> int:
        """Steps the learned line time is held: a fit whose motion starts from the translation search,
        unless it started from another fit (its fields or its line time)."""
        inherited = self._pose_inherited or self._line_inherited
        return self.fit_config.line_hold_steps_search if self._search_started() and not inherited else 0

    def _search_started(self) -> bool:
        """Whether this fit's motion starts from the translation search (the prior preset)."""
        return self.parts.motion and self.resolved.motion_init == "search" and not self.resolved.dynamic_time

    def _ratio(self, group: dict) -> float:
        """A parameter group's learning rate per unit of the fields' at this step (0 while it is held)."""
        return 0.0 if self.steps < group.get("hold_steps", 0) else group["lr_ratio"]

    def _update_group(self, param: nn.Parameter, **changes) -> None:
        """Change the schedule of the optimiser group that steps `param` (a start from another fit)."""
        for g in self.optimiser.param_groups:
            if any(q is param for q in g["params"]):
                g.update(changes)

    # ------------------------------------------------------------------ Method protocol

    def _lr_now(self) -> float:
        half = self.resolved.lr_half_life_steps
        decay = 1.0 if not math.isfinite(half) else max(0.5 ** (self.steps / half), 0.05)
        return self.base_lr * decay

    def step(self) -> float:
        self._cache = None  # the last evaluated video goes before this step's graph is built
        lr = self._lr_now()
        for g in self.optimiser.param_groups:
            g["lr"] = lr * self._ratio(g)
        rows = self.sample_rows() if self.parts.rs else None
        tv_frames = self.sample_tv_frames() if (self.parts.motion and self.parts.motion_reg) else None
        windows = None
        n_win = self.resolved.gs_windows_per_step
        if self.parts.gs and n_win and n_win < self.w_gs.shape[0]:
            windows = torch.randperm(self.w_gs.shape[0], generator=self.generator)[:n_win].sort().values
        with heap_reuse():  # a large grid's temporaries are not faulted in afresh every step
            # freed inside: outside, glibc trimmed the heap top the last step's gradients held
            self.optimiser.zero_grad(set_to_none=True)
            terms = self.loss_terms(rows, tv_frames, backward=True, gs_windows=windows)
            self.optimiser.step()
        self.steps += 1
        if self._ema is not None:  # warm-up as in TF's ExponentialMovingAverage(num_updates)
            decay = min(self.resolved.ema_decay, (1 + self.steps) / (10 + self.steps))
            with torch.no_grad():
                for a, q in zip(self._ema, self._params, strict=True):
                    a.lerp_(q, 1 - decay)
        self._cache = None
        return sum(terms.values())

    def fit_step(self) -> tuple[float, str | None]:
        """One step and the stop test after it (an ensemble's member, in its lane), without
        keeping the stop test's video."""
        value = self.step()
        done = self.converged()
        self._cache = None
        return value, done

    @contextmanager
    def _averaged(self):
        """Inside: the weights are their moving average (outputs, residuals, the stop test)."""
        if self._ema is None:
            yield
            return
        with torch.no_grad():
            current = [q.detach().clone() for q in self._params]
            for q, a in zip(self._params, self._ema, strict=True):
                q.copy_(a)
        try:
            yield
        finally:
            with torch.no_grad():
                for q, c in zip(self._params, current, strict=True):
                    q.copy_(c)


    @torch.no_grad()
    def estimate(self) -> Tensor:
        if self._cache is not None and self._cache[0] == self.steps:
            return self._cache[1]
        video = torch.empty(self.C, self.K, self.H, self.W, device=self.device)
        if self.device.type == "cpu":  # the steps' freed heap pages go before a large video's buffer comes
            release_before(video.numel() * video.element_size())
        with self._averaged(), self._decoded_once():
            for idx in _chunks(torch.arange(self.K, device=self.device), self.frame_chunk):
                video[:, idx] = self._video_frames(idx)
        self._cache = (self.steps, video)
        return video

    @torch.no_grad()
    def residuals(self) -> dict[str, float]:
        return self.residuals_of(self.estimate(), self.gains())  # both from the averaged weights

    @torch.no_grad()
    def residuals_of(self, video: Tensor, gains: np.ndarray, line_factor: float | None = None) -> dict[str, float]:
        """Relative RS and GS residuals of a video (C, K, H, W) with GS/RS gains (C,) (and the RS
        rows at `line_factor`, default: this fit's where it learns one)."""
        out = {}
        self._sync_rs_op(line_factor)
        if self.problem.b_rs is not None:
            pred = self.rs_op.A(video, frame_chunk=self.frame_chunk)
            target = self.problem.b_rs
            if self.rs_valid is not None:
                pred, target = pred * self.rs_valid, target * self.rs_valid
            out["rs"] = relative_residual(pred, target)
        if self.problem.b_gs is not None and self.problem.b_gs.shape[1] > 0:
            pred, seen = self._gs_view(self.gs_op.A(video))
            target = torch.from_numpy(gains).to(self.device)[:, None, None, None] * self.problem.b_gs
            if seen is not None:
                pred, target = pred * seen, target * seen
            if self.mask is not None:
                pred, target = pred * self.mask, target * self.mask
            if self.gs_valid is not None:
                pred, target = pred * self.gs_valid, target * self.gs_valid
            out["gs"] = relative_residual(pred, target)
        return out

    @torch.no_grad()
    def components(self) -> dict[str, np.ndarray]:
        """static (C, H, W), alpha (1, K, H, W) and motion (2, K, H, W, in pixels) as numpy."""
        with self._averaged():
            return self._components()

    def _components(self) -> dict[str, np.ndarray]:
        static = self._static() if self.parts.static else torch.zeros(self.C, self.H, self.W, device=self.device)
        alpha = torch.ones(1, self.K, self.H, self.W, device=self.device) if self.parts.static else \
            torch.zeros(1, self.K, self.H, self.W, device=self.device)
        motion = torch.zeros(2, self.K, self.H, self.W, device=self.device)
        if self.parts.motion:
            for idx in _chunks(torch.arange(self.K, device=self.device), self.frame_chunk):
                u = self._motion(idx)
                total = u[..., :2] + (self.key_flow[idx][..., :2] if self._key_warps else 0)
                motion[:, idx] = (total * self.px_per_unit).permute(3, 0, 1, 2)
                if self.parts.static:
                    alpha[:, idx] = self._dynamic_at(u, idx)[1]
        return {"static": static.cpu().numpy(), "alpha": alpha.cpu().numpy(), "motion": motion.cpu().numpy()}

    def gains(self) -> np.ndarray:
        with self._averaged():
            return self._gain().detach().cpu().numpy()

    def pose(self) -> Tensor | None:
        """The learned GS-to-RS pose (4,) (averaged weights), None where the fit does not learn it."""
        if not self.learn_pose:
            return None
        with self._averaged():
            return (self.gs_pose * self.pose_free).detach().clone()

    @torch.no_grad()
    def _start_param(self, param: nn.Parameter, value: Tensor) -> None:
        """Set `param` and its moving average to `value` (another fit's start)."""
        param.copy_(value.to(param))
        if self._ema is not None:
            self._ema[next(i for i, q in enumerate(self._params) if q is param)].copy_(param)

    def start_pose(self, pose: Tensor) -> None:
        """Start the learned pose (and its moving average) at `pose` (another fit's, same grid)."""
        self._start_param(self.gs_pose, pose)
        self._pose_inherited = True
        self._update_group(self.gs_pose, **self._pose_schedule())

    def learned_geometry(self) -> dict | None:
        return geometry_report(self.pose(), self.pose_radius, self.state.selfcal_report)

    def state_dict(self) -> dict:
        return {"fields": self.fields.state_dict(), "log_gain": self.log_gain.detach().clone(),
                "gs_pose": self.gs_pose.detach().clone(), "line_shift": self.line_shift.detach().clone(),
                "optimiser": self.optimiser.state_dict(), "steps": self.steps, "base_lr": self.base_lr,
                "generator": self.generator.get_state(), "rs_history": dict(self._rs_history),
                "ema": None if self._ema is None else [a.clone() for a in self._ema]}

    def load_state_dict(self, state: dict) -> None:
        self.fields.load_state_dict(state["fields"])
        with torch.no_grad():
            self.log_gain.copy_(state["log_gain"])
            if "gs_pose" in state:
                self.gs_pose.copy_(state["gs_pose"])
            if "line_shift" in state:
                self.line_shift.copy_(state["line_shift"])
        self.optimiser.load_state_dict(state["optimiser"])
        self.steps = int(state["steps"])
        self.base_lr = float(state["base_lr"])
        self.generator.set_state(state["generator"])
        self._rs_history = dict(state.get("rs_history", {}))
        if self._ema is not None and state.get("ema") is not None:
            with torch.no_grad():
                for a, saved in zip(self._ema, state["ema"], strict=True):
                    a.copy_(saved)
        self._cache = None

    def budget_cut(self) -> str:
        """Said when a time budget ends the run: how far the fit was from its own stop."""
        if not self._rs_history:
            return "the fit had not reached its first convergence check"
        step = max(self._rs_history)
        noise = f"; noise level {self.rs_noise_level:.4f}" if self.rs_noise_level is not None else ""
        return (f"the fit had not converged (RS residual {self._rs_history[step]:.4f} at step {step}{noise}); "
                "its output is the state at the budget")

    def reduce_step(self, factor: float) -> None:
        self.base_lr *= factor
        for g in self.optimiser.param_groups:
            g["lr"] = self._lr_now() * g["lr_ratio"]

    def resolved_settings(self) -> dict:
        """The settings as used (preset values filled in), for the outputs."""
        out = asdict(self.resolved.settings)
        out.update({k: getattr(self.resolved, k) for k in (*_FROM_PRESET, "rows_per_step")})
        out["frame_chunk"] = self.frame_chunk
        out["base_video"] = self.base_source
        out["rs_noise_level"] = self.rs_noise_level
        out["preset_choice"] = self.state.preset_choice
        out["fields"] = {k: [v[0], dict(v[1])] for k, v in self.resolved.fields.items()}
        out["left_out"] = [list(x) for x in self.left_out]
        report = self.state.selfcal_report
        if ablation.selfcal_note(self.settings):
            out["self_calibration"] = {"mode": "off", "why": ablation.selfcal_off(self.settings)}
        if report:
            out["self_calibration"] = dict(report)
            if report.get("applied"):  # the fit learns the gains further (Lambda, on the refined scale)
                learned = self.gains() if self.learn_gain else np.ones(self.C)
                end = [float(g) * r for g, r in zip(learned, report["refined"]["gains"], strict=True)]
                out["self_calibration"]["end"] = {**report["refined"], "gains": end}
        return add_learned(out, self)


def learned_notes(method) -> list[str]:
    """The notes on what a fit (an STFM or an ensemble) learned with its fields."""
    return (geometry_lines(method.learned_geometry(), method.steps)
            + line_time_lines(method.line_time_report(), method.steps))


def add_learned(out: dict, method) -> dict:
    """Resolved settings `out` with what a fit learned with its fields: gs_geometry (whose end is
    also self-calibration's end, where that applied a calibration) and line_time."""
    geometry, line = method.learned_geometry(), method.line_time_report()
    if geometry is not None:
        out["gs_geometry"] = geometry
        if out.get("self_calibration", {}).get("end"):
            out["self_calibration"]["end"].update(geometry["end"])
    if line is not None:
        out["line_time"] = line
    return out


def geometry_report(pose: Tensor | None, radius: float, selfcal: dict | None) -> dict | None:
    """{"start" (the transform the GS frames were taken to RS coordinates by before the fit),
    "learned" (the fit's on top of it), "end" (both: what the rig has)} as shift / rotation / scale."""
    if pose is None:
        return None
    start = similarity()
    if selfcal and selfcal.get("applied") and "transform_not_applied" not in selfcal:
        r = selfcal["refined"]
        start = similarity(*r["shift_px"], np.radians(r["rotation_deg"]), r["scale"])
    learned = pose_matrix(pose.double().cpu(), radius).numpy()
    return {"start": describe(start), "learned": describe(learned), "end": describe(learned @ start)}


def geometry_lines(geometry: dict | None, steps: int) -> list[str]:
    """The note on the learned GS-to-RS transform (none before the first step)."""
    if geometry is None or steps == 0:
        return []
    e = geometry["end"]
    return [f"GS-to-RS transform learned with the fields: shift ({e['shift_px'][0]:+.3f}, {e['shift_px'][1]:+.3f}) px, "
            f"rotation {e['rotation_deg']:+.3f} deg, scale {e['scale']:.4f}"]
