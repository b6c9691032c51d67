"""The STFM method: one fit (settings resolved, its parts built, optimiser, steps, outputs, checkpoints)."""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import asdict

import numpy as np
import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.memory import heap_reuse, release_before
from rngcam.recon import ablation
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.selfcal import report_lines
from rngcam.recon.methods.stfm.bases import DynamicBase
from rngcam.recon.methods.stfm.components import Components, choose_components
from rngcam.recon.methods.stfm.fields import transfer_fields
from rngcam.recon.methods.stfm.flat_adam import FlatAdam, flatten
from rngcam.recon.methods.stfm.grid import FitGrid, chunks, sorted_sample
from rngcam.recon.methods.stfm.init import GSInit
from rngcam.recon.methods.stfm.learned import Gains, Pose, geometry_lines
from rngcam.recon.methods.stfm.line_time import LineTime, line_time_lines
from rngcam.recon.methods.stfm.loss import DataLoss
from rngcam.recon.methods.stfm.model import FieldModel
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

# The moving average's decay warms up as TF's ExponentialMovingAverage(num_updates): min(decay, (1 + n) / (this + n))
EMA_WARMUP_STEPS = 10


def _group_ratio(group: dict, steps: int) -> float:
    """A parameter group's learning rate per unit of the fields' at `steps` (0 while it is held)."""
    return 0.0 if steps < group.get("hold_steps", 0) else group["lr_ratio"]


def _spans(params: list[Tensor]) -> list[tuple[int, int]]:
    """(start, end) of each parameter in a buffer that holds them one after another (`flatten`)."""
    ends = np.cumsum([0] + [q.numel() for q in params]).tolist()
    return list(zip(ends[:-1], ends[1:], strict=True))


class STFM(MethodBase):
    """STFM as a `rngcam.recon.loop.Method`: one fit. Build it with `make_stfm`. Its parts are objects
    of the package's modules: what it sees of the problem (`grid`: grid.FitGrid), the fields and the
    frames they make (`model`: model.FieldModel, on a `base`: bases.DynamicBase), what it learns of the
    rig (`learned_gains`, `learned_pose`, `learned_line_time`: learned.Learned), its objective (`loss`:
    loss.DataLoss) and its stop test (`stop`: stopping.NoiseStop); this class steps them (optimiser,
    moving average) and answers for the fit (outputs, checkpoints)."""

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
        self.notes_at_build = [f"preset auto chose {choice['preset']}: {choice['reason']}"] if choice else []
        self.notes_at_build += report_lines(self.state.selfcal_report)  # the end values: resolved_settings
        self.notes_at_build += ablation.selfcal_note(settings)  # --no-gs / --no-rs: nothing to calibrate against
        self.static_from = static_from
        self.device = torch.device(device)
        self.problem = problem.to(torch.float32, self.device)
        p = self.problem
        p.check_finite("stfm")
        self.C, self.K, self.H, self.W = p.shape
        self.resolved, preset = resolve(settings, self.H, self.W, self.K)
        self.frame_chunk = chunk_frames(settings, self.H, self.W, str(self.device))
        self.parts: Components = choose_components(
            problem, auto=settings.components == "auto", no_static=settings.no_static,
            no_motion_reg=settings.no_motion_reg, no_rs=settings.no_rs, no_gs=settings.no_gs, tau=self.resolved.tau,
            config=self.fit_config)
        if "," in self.resolved.dynamic_base or self.resolved.dynamic_base == "ensemble":
            raise ConfigError(f"dynamic_base {self.resolved.dynamic_base!r} is an ensemble: build it with make_stfm")
        torch.manual_seed(settings.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(settings.seed)
        self.grid = FitGrid(p, self.parts, settings.gs_anchor, self.frame_chunk, self.device, self.fit_config)
        self.learned_line_time = LineTime(p, self.device)
        self.base = DynamicBase(self.grid, p, self.resolved, self.parts, base_video, base_gains)
        self.learned_gains = Gains(p.white_balance, self.C, preset["gain_lr_ratio"], self.parts.rs and self.parts.gs,
                                   self.device)
        self.learned_pose = Pose(self.H, self.W, self.device)
        self.model = FieldModel(self.grid, self.parts, self.resolved, settings.gs_anchor, self.base,
                                self.learned_gains, self.learned_pose, p, preset)
        self.loss = DataLoss(self.model, self.learned_line_time, settings, self.generator, rs_norm_start)
        self.stop = NoiseStop(self)
        # kept for a next level's warm start (a video-sized buffer the caller frees); None without a start
        self.rs_norm_vector, self.loss.rs_norm_vector = self.loss.rs_norm_vector, None
        if fields_from is not None:
            transfer_fields(self.model.fields, fields_from.model.fields)
            self.learned_gains.transfer(fields_from.learned_gains, 1.0)
            self.learned_pose.transfer(fields_from.learned_pose, self.W / fields_from.W)
            if fields_from.learned_line_time.timing is not None:
                self.learned_line_time.transfer(fields_from.learned_line_time, self.learned_line_time.readout_frames
                                                / fields_from.learned_line_time.readout_frames)
        elif self.resolved.init == "gs" and self.parts.gs:
            GSInit(self).run()
        self.steps = 0
        self._params = [*self.model.fields.parameters(), self.learned_gains.parameter,
                        self.learned_line_time.parameter, self.learned_pose.parameter]
        # one buffer for all parameters: the optimiser's update and the moving average are a few
        # operations a step, not a few per parameter (None: parameters of several dtypes or devices)
        same = len({(q.dtype, q.device) for q in self._params}) == 1
        self._flat = flatten(self._params) if same else None
        self._build_optimiser(preset)
        self._ema_flat, self._ema = None, None
        if self.resolved.ema_decay > 0 and self._flat is not None:
            self._ema_flat = self._flat.clone()
            self._ema = [self._ema_flat[a:b].view_as(q) for q, (a, b) in zip(self._params, _spans(self._params),
                                                                              strict=True)]
        elif self.resolved.ema_decay > 0:
            self._ema = [q.detach().clone() for q in self._params]
        self._cache: tuple[int, Tensor] | None = None
        rows = self.grid.rs_rows_fit.to(self.device)
        self.rs_noise_level = relative_noise_level(p.b_rs.index_select(1, rows)) if self.parts.rs else None

    # ------------------------------------------------------------------ setup

    @property
    def notes(self) -> list[str]:
        return self.notes_at_build + learned_notes(self)

    @property
    def left_out(self) -> list[tuple[str, str]]:
        """Components left out and substitutes used (e.g. no RIFE weights), each with why."""
        return list(self.parts.left_out) + list(self.base.substitutes)

    def _build_optimiser(self, preset: dict) -> None:
        """Adam over the fields (planes, then decoders at the preset's ratio) and, in groups of their own
        on their own schedules, what the fit learns of the rig."""
        lr = self.resolved.lr
        planes, decoders = [], []
        for module in self.model.fields.values():
            for pname, param in module.named_parameters():
                (planes if pname.startswith("planes") else decoders).append(param)
        groups = [{"params": planes, "lr_ratio": 1.0}] if planes else []
        if decoders:
            ratio = preset["decoder_lr_ratio"] if planes else 1.0
            groups.append({"params": decoders, "lr_ratio": ratio})
        gains, pose, line = self.learned_gains, self.learned_pose, self.learned_line_time
        if gains.learned:
            groups.append({"params": [gains.parameter], **gains.schedule()})
        mode, soft = self.settings.learn_geometry, self.settings.gs_anchor == "soft"
        pose.enable(mode, gains.learned and mode != "off" and soft, self.fit_config)
        if pose.learned:
            groups.append({"params": [pose.parameter], **pose.schedule()})
        wanted, note = line.wanted(self.settings)
        self.notes_at_build += [note] if note else []
        line.enable(wanted and gains.learned and soft, self.fit_config, self.search_started())
        if line.learned:
            groups.append({"params": [line.parameter], **line.schedule(pose.inherited)})
        for g in groups:
            g["lr"] = lr * _group_ratio(g, self.steps)
        if self._flat is not None:  # Adam's update on the one buffer (flat_adam)
            self.optimiser = FlatAdam(groups, self._flat, lr=lr)
        else:  # fused: one kernel for all parameters (CPU and CUDA; bench/convergence.md)
            self.optimiser = torch.optim.Adam(groups, lr=lr, fused=self.device.type in ("cpu", "cuda"))
        self.base_lr = lr

    def search_started(self) -> bool:
        """Whether this fit's motion starts from the translation search (the prior preset)."""
        return self.parts.motion and self.resolved.motion_init == "search" and not self.resolved.dynamic_time

    def _start_learned(self, learned, value: Tensor, schedule: dict) -> None:
        """Start a learned quantity (and its moving average) at `value` (another fit's, same grid) and
        step it on `schedule` from now on."""
        param = learned.parameter
        with torch.no_grad():
            param.copy_(value.to(param))
            if self._ema is not None:
                self._ema[next(i for i, q in enumerate(self._params) if q is param)].copy_(param)
        for g in self.optimiser.param_groups:
            if any(q is param for q in g["params"]):
                g.update(schedule)

    # ------------------------------------------------------------------ Method protocol

    def _lr_now(self) -> float:
        half = self.resolved.lr_half_life_steps
        decay = 1.0 if not math.isfinite(half) else max(0.5 ** (self.steps / half), self.fit_config.lr_floor_share)
        return self.base_lr * decay

    def step(self) -> float:
        self._cache = None  # the last evaluated video goes before this step's graph is built
        lr = self._lr_now()
        for g in self.optimiser.param_groups:
            g["lr"] = lr * _group_ratio(g, self.steps)
        rows = self.loss.sample_rows() if self.parts.rs else None
        tv_frames = self.loss.sample_tv_frames() if (self.parts.motion and self.parts.motion_reg) else None
        windows = None
        n_win, n_gs = self.resolved.gs_windows_per_step, self.grid.w_gs.shape[0]
        if self.parts.gs and n_win and n_win < n_gs:
            windows = self.loss.step_indices(sorted_sample(n_gs, n_win, self.generator))
        with heap_reuse():  # a large grid's temporaries are not faulted in afresh every step
            # freed inside: outside, glibc trimmed the heap top the last step's gradients held
            self.optimiser.zero_grad(set_to_none=True)
            terms = self.loss.loss_terms(rows, tv_frames, backward=True, gs_windows=windows)
            self.optimiser.step()
        self.steps += 1
        if self._ema is not None:
            decay = min(self.resolved.ema_decay, (1 + self.steps) / (EMA_WARMUP_STEPS + self.steps))
            with torch.no_grad():
                if self._ema_flat is not None:
                    self._ema_flat.lerp_(self._flat, 1 - decay)
                else:
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

    def converged(self) -> str | None:
        return self.stop.converged()

    def log_ready(self) -> bool:
        return self.stop.log_ready()

    def _fits_every_row(self) -> bool:
        return len(self.grid.rs_rows_fit) == self.H

    def fit_every_row(self) -> bool:
        """Fit the held-out RS rows too from this step on (the self-check has judged: stfm.floor), the stop
        test started afresh on every row; False where every row is fitted already."""
        if not self.parts.rs or self._fits_every_row():
            return False
        self.grid.rs_rows_fit = torch.arange(self.H)
        self.loss.fit_rows(self.grid.rs_rows_fit)
        self.rs_noise_level = relative_noise_level(self.problem.b_rs)
        self.stop.restart()
        self._cache = None
        return True

    @contextmanager
    def averaged(self):
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
        with self.averaged(), self.model.decoded_once():
            for idx in chunks(torch.arange(self.K, device=self.device), self.frame_chunk):
                video[:, idx] = self.model.video_frames(idx)
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
        self.sync_line_time(line_factor)
        grid = self.grid
        if self.problem.b_rs is not None:
            pred = grid.rs_op.A(video, frame_chunk=self.frame_chunk)
            target = self.problem.b_rs
            if grid.rs_valid is not None:
                pred, target = pred * grid.rs_valid, target * grid.rs_valid
            out["rs"] = relative_residual(pred, target)
        if self.problem.b_gs is not None and self.problem.b_gs.shape[1] > 0:
            pred, seen = self.learned_pose.gs_view(grid.gs_op.A(video))
            target = torch.from_numpy(gains).to(self.device)[:, None, None, None] * self.problem.b_gs
            for mask in (seen, grid.mask, grid.gs_valid):
                if mask is not None:
                    pred, target = pred * mask, target * mask
            out["gs"] = relative_residual(pred, target)
        return out

    @torch.no_grad()
    def components(self) -> dict[str, np.ndarray]:
        """static (C, H, W), alpha (1, K, H, W) and motion (2, K, H, W, in pixels) as numpy."""
        with self.averaged():
            return self.model.components()

    def gains(self) -> np.ndarray:
        with self.averaged():
            return self.learned_gains.value().detach().cpu().numpy()

    def pose(self) -> Tensor | None:
        """The learned GS-to-RS pose (4,) (averaged weights), None where the fit does not learn it."""
        with self.averaged():
            return self.learned_pose.reading()

    def line_factor(self) -> float | None:
        """The learned line-time factor (averaged weights), None where the fit does not learn it."""
        if not self.learned_line_time.learned:
            return None
        with self.averaged():
            return float(self.learned_line_time.factor_tensor().detach())

    def sync_line_time(self, factor: float | None = None) -> None:
        """The RS operator at `factor` (default: the averaged learned one, where the fit learns one)."""
        self.learned_line_time.sync(self.grid, self.line_factor() if factor is None else factor)

    def start_pose(self, pose: Tensor) -> None:
        """Start the learned pose (and its moving average) at `pose` (another fit's, same grid)."""
        self.learned_pose.inherited = True
        self._start_learned(self.learned_pose, pose, self.learned_pose.schedule())

    def start_line_factor(self, factor: float) -> None:
        """Start the learned factor (and its moving average) at `factor` (another fit's), and learn
        it from the next step on (no hold)."""
        line = self.learned_line_time
        line.inherited = True
        self._start_learned(line, line.start_value(factor), line.schedule(self.learned_pose.inherited))

    def learned_geometry(self) -> dict | None:
        return self.learned_pose.report(self.pose(), self.state.selfcal_report)

    def line_time_report(self) -> dict | None:
        return self.learned_line_time.report(self.line_factor(), self.state.line_time_from)

    def state_dict(self) -> dict:
        return {"fields": self.model.fields.state_dict(), "log_gain": self.learned_gains.parameter.detach().clone(),
                "gs_pose": self.learned_pose.parameter.detach().clone(),
                "line_shift": self.learned_line_time.parameter.detach().clone(),
                "optimiser": self.optimiser.state_dict(), "steps": self.steps, "base_lr": self.base_lr,
                "generator": self.generator.get_state(), "rs_history": dict(self.stop.history),
                "every_row": self._fits_every_row(), "stop_not_before": self.stop.not_before,
                "ema": None if self._ema is None else [a.clone() for a in self._ema]}

    def load_state_dict(self, state: dict) -> None:
        self.model.fields.load_state_dict(state["fields"])
        with torch.no_grad():
            self.learned_gains.parameter.copy_(state["log_gain"])
            if "gs_pose" in state:
                self.learned_pose.parameter.copy_(state["gs_pose"])
            if "line_shift" in state:
                self.learned_line_time.parameter.copy_(state["line_shift"])
        self.optimiser.load_state_dict(state["optimiser"])
        self.steps = int(state["steps"])
        self.base_lr = float(state["base_lr"])
        self.generator.set_state(state["generator"])
        if state.get("every_row"):
            self.fit_every_row()
        self.stop.history = dict(state.get("rs_history", {}))
        self.stop.not_before = int(state.get("stop_not_before", 0))
        if self._ema is not None and state.get("ema") is not None:
            with torch.no_grad():
                for a, saved in zip(self._ema, state["ema"], strict=True):
                    a.copy_(saved)
        self._cache = None

    def budget_cut(self) -> str:
        """Said when a time budget ends the run: how far the fit was from its own stop."""
        history = self.stop.history
        if not history:
            return "the fit had not reached its first convergence check"
        step = max(history)
        noise = f"; noise level {self.rs_noise_level:.4f}" if self.rs_noise_level is not None else ""
        return (f"the fit had not converged (RS residual {history[step]:.4f} at step {step}{noise}); "
                "its output is the state at the budget")

    def end_fit(self) -> None:
        """The run is over: the gradients and Adam's moments (three buffers the size of the parameters)
        and the cached video go before the components and outputs are made; step() and state_dict()
        no longer work (bench/convergence.md, seventh round)."""
        self._cache = None
        for q in self._params:
            q.grad = None
        self.optimiser = None

    def reduce_step(self, factor: float) -> None:
        self.base_lr *= factor
        for g in self.optimiser.param_groups:
            g["lr"] = self._lr_now() * g["lr_ratio"]

    def resolved_settings(self) -> dict:
        """The settings as used (preset values filled in), for the outputs."""
        out = asdict(self.resolved.settings)
        out.update({k: getattr(self.resolved, k) for k in (*_FROM_PRESET, "rows_per_step")})
        out["frame_chunk"] = self.frame_chunk
        out["base_video"] = self.base.source
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
                learned = self.gains() if self.learned_gains.learned else np.ones(self.C)
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
