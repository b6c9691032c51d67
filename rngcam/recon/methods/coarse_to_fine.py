"""Coarse-to-fine reconstruction: a coarser Problem in space and time, and a Method wrapper that
runs any iterative method from the coarsest level to the full grid, each level starting from the
previous level's estimate upsampled.

A coarse level bins `factor` x `factor` grid pixels and `factor` frames (area weights, so sizes
need not divide): with R (H', H) and X (W', W) the row/column averaging matrices and S (K', K)
the 0/1 frame blocks, the coarse RS weights are R W_rs S^T, the GS weights W_gs S^T, the
measurements R b X^T, and the PSF is area-resampled by the same spatial factor. If v' is a coarse
video and U its nearest-neighbour upsampling, A'(v') = bin(A(U v')) up to the PSF's resampling,
so a coarse fit is a cheap, consistent start for the next level. Set-up work that does not scale
(operator norms, GS-only starts) runs per level, inside the level's first step.

A method plugs in through `make(problem, x0)`: build the method on `problem`, starting from the
video `x0` (C, K, H, W) when it is not None (the coarsest level gets None: the method's own start).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from rngcam.memory import release_free_memory
from rngcam.physics import psf as psf_mod
from rngcam.physics.timing import VideoGrid
from rngcam.recon.checkpoint import Kept, kept  # noqa: F401 - pnp and tv3d import them from here
from rngcam.recon.loop import Clock, MethodBase
from rngcam.recon.problem import Problem


def area_matrix(n_out: int, n_in: int, dtype=torch.float64) -> Tensor:
    """(n_out, n_in) rows of overlap weights, each summing to 1: output cell i averages input
    cells over [i n_in / n_out, (i + 1) n_in / n_out)."""
    edges = np.arange(n_out + 1) * n_in / n_out
    m = np.zeros((n_out, n_in))
    for i in range(n_out):
        lo, hi = edges[i], edges[i + 1]
        for j in range(int(math.floor(lo)), min(int(math.ceil(hi)), n_in)):
            m[i, j] = min(hi, j + 1) - max(lo, j)
    return torch.from_numpy(m / m.sum(axis=1, keepdims=True)).to(dtype)


def block_matrix(n_out: int, n_in: int, block: int, dtype=torch.float64) -> Tensor:
    """(n_out, n_in) 0/1: output frame i sums input frames [i block, (i + 1) block)."""
    m = torch.zeros(n_out, n_in, dtype=dtype)
    for i in range(n_out):
        m[i, i * block:(i + 1) * block] = 1
    return m


def linear_matrix(n_out: int, n_in: int, step: float, dtype=torch.float64) -> Tensor:
    """(n_out, n_in) linear interpolation: output cell j's centre lies at input coordinate
    (j + 0.5) / step - 0.5 (step = output cells per input cell), clamped at the ends."""
    src = ((torch.arange(n_out, dtype=torch.float64) + 0.5) / step - 0.5).clamp(0, n_in - 1)
    lo = src.floor().long().clamp(max=n_in - 1)
    hi = (lo + 1).clamp(max=n_in - 1)
    frac = src - lo
    m = torch.zeros(n_out, n_in, dtype=torch.float64)
    m[torch.arange(n_out), lo] += 1 - frac
    m[torch.arange(n_out), hi] += frac
    return m.to(dtype)


def _bin2(img: Tensor, r: Tensor, x: Tensor) -> Tensor:
    """(..., H, W) -> (..., H', W') with row matrix r (H', H) and column matrix x (W', W)."""
    return r.to(img) @ img @ x.to(img).T


# A coarse level keeps the GS frames of a source grid up to this many pixels (Problem.fine_gs): its
# GS-only videos and flows are computed there, where RIFE sees the detail it needs.
FINE_GS_MAX_PIXELS = 128 * 128


def coarsen(problem: Problem, factor: int, time_factor: int | None = None) -> Problem:
    """The problem on a grid `factor` times coarser in space and `time_factor` (default: the same)
    in time. A held-out split of RS rows is carried over: a coarse row is fitted only where every
    source row it bins is (so no coarse fit sees a held-out row); held-out GS pixels are not (the
    coarse level's GS-only videos are made from the source grid's frames). The source grid's GS
    frames go along as `fine_gs` where it has at most FINE_GS_MAX_PIXELS."""
    if problem.gs_train_mask is not None:
        raise ValueError("coarse-to-fine does not support held-out GS pixels")
    s, t = int(factor), int(time_factor or factor)
    c, k, h, w = problem.shape
    h2, w2, k2 = max(1, round(h / s)), max(1, round(w / s)), math.ceil(k / t)
    r, x = area_matrix(h2, h), area_matrix(w2, w)
    frames = block_matrix(k2, k, t)
    rs_w = r.to(problem.rs_weights) @ problem.rs_weights @ frames.to(problem.rs_weights).T
    gs_w = problem.gs_weights @ frames.to(problem.gs_weights).T
    psf = torch.from_numpy(psf_mod.bin_psf(problem.psf.double().cpu().numpy(), s))  # exact for s x s blocks
    truth = None if problem.truth is None else bin_video(problem.truth, (c, k2, h2, w2), t)

    def bin_valid(valid):
        return None if valid is None else _bin2(valid.double(), r, x) > 1 - 1e-9

    return Problem(
        b_rs=None if problem.b_rs is None else _bin2(problem.b_rs, r, x),
        b_gs=None if problem.b_gs is None else _bin2(problem.b_gs, r, x),
        rs_weights=rs_w, gs_weights=gs_w, psf=psf.to(problem.psf), grid=VideoGrid(problem.grid.dt_s * t, k2),
        gs_times_s=problem.gs_times_s, truth=truth,
        mask=None if problem.mask is None else _bin2(problem.mask.double(), r, x) > 0.5,
        white_balance=problem.white_balance, notes=[], time_origin_s=problem.time_origin_s,
        rs_valid=bin_valid(problem.rs_valid), gs_valid=bin_valid(problem.gs_valid), fine_gs=_fine_gs(problem),
        subframes=max(1, problem.subframes // t),  # frames t x longer: fewer of them to an output frame
        rs_train_rows=_coarse_train_rows(problem.rs_train_rows, r))


def _coarse_train_rows(rows: Tensor | None, r: Tensor) -> Tensor | None:
    """The coarse rows (binned by `r`) that bin fitted source rows only; None without a split."""
    if rows is None:
        return None
    held = r.to(torch.float64) @ (~rows).to(torch.float64).cpu()
    return (held <= 0).to(rows.device)


def _fine_gs(problem: Problem) -> Tensor | None:
    """The GS frames a level binned from `problem` computes its GS-only videos on (None: its own)."""
    if problem.fine_gs is not None:
        return problem.fine_gs
    if problem.b_gs is None or problem.b_gs.shape[-2] * problem.b_gs.shape[-1] > FINE_GS_MAX_PIXELS:
        return None
    return problem.gs_images()


def bin_space(video: Tensor, height: int, width: int) -> Tensor:
    """(..., H, W) -> (..., height, width) by area, as `coarsen` bins the measurements."""
    h, w = video.shape[-2:]
    return _bin2(video, area_matrix(height, h), area_matrix(width, w))


def bin_video(video: Tensor, shape: tuple[int, int, int, int], time_factor: int) -> Tensor:
    """(C, K, H, W) -> `shape` (C, K', H', W'): frames averaged in blocks of `time_factor`, pixels
    by area (how `coarsen` bins the truth)."""
    _, k, h, w = video.shape
    _, k2, h2, w2 = shape
    frames = block_matrix(k2, k, time_factor)
    mean = (frames / frames.sum(1, keepdim=True).clamp_min(1)).to(video)
    return _bin2(torch.einsum("jk,ckhw->cjhw", mean, video), area_matrix(h2, h), area_matrix(w2, w))


def upsample(video: Tensor, shape: tuple[int, int, int, int], time_factor: float, dtype=None,
             frames: int = 16) -> Tensor:
    """(C, K', H', W') -> (C, K, H, W) by separable linear interpolation; frame centres map by
    `time_factor` (fine frames per coarse frame), pixels by the size ratio (area-consistent).
    Computed in video's dtype, `frames` output frames at a time, into a tensor of `dtype`
    (default: video's)."""
    c, k, h, w = shape
    _, k2, h2, w2 = video.shape
    mt = linear_matrix(k, k2, time_factor).to(video)
    my, mx = linear_matrix(h, h2, h / h2).to(video), linear_matrix(w, w2, w / w2).to(video)
    out = torch.empty((video.shape[0], k, h, w), dtype=dtype or video.dtype, device=video.device)
    for i in range(0, k, frames):
        part = torch.einsum("kj,cjhw->ckhw", mt[i:i + frames], video)
        out[:, i:i + frames] = my @ part @ mx.T
    return out


def power_norm(op, x0: Tensor, iters: int = 20, tol: float = 1e-3) -> tuple[float, Tensor]:
    """(||op||, the last iterate) by power iteration on A^T A from `x0`: from a coarser level's
    vector, upsampled, it settles in a few iterations instead of twenty. `x0` is consumed (scaled
    in place where it already has the operator's dtype); the iterates live in it and one more
    video-sized buffer."""
    n0 = float(x0.norm())
    if not (math.isfinite(n0) and n0 > 0):  # a zero or non-finite start has no direction: start anew
        x0 = torch.ones_like(x0)
        n0 = float(x0.norm())
    x = x0.div_(n0)
    lam = 0.0
    for _ in range(iters):
        z = op.A_normal(x)
        new, nz = inner(x, z), float(z.norm())
        if nz == 0.0:
            return 0.0, x
        del x  # the previous iterate goes before the next one is needed
        x = z.div_(nz)
        if abs(new - lam) <= tol * max(abs(new), 1e-30):
            lam = new
            break
        lam = new
    return math.sqrt(max(lam, 0.0)), x


def inner(a: Tensor, b: Tensor, frames: int = 16) -> float:
    """<a, b> of two videos, summed `frames` frames at a time (no video-sized product)."""
    return sum(float((a[:, i:i + frames] * b[:, i:i + frames]).sum()) for i in range(0, a.shape[1], frames))


# What a coarse-to-fine level's start (the coarser estimate, upsampled) is kept in: a storage format
# (methods compute in float32); 3 significant digits, far below any measurement's noise.
START_DTYPE = torch.float16


def default_factors(shape: tuple[int, int, int, int], min_side: int = 48) -> tuple[int, ...]:
    """Spatial factors from coarse to fine, halving while the coarse grid keeps >= min_side px on
    its short side: (4, 2, 1) at 228x342, (2, 1) at 128, (1,) at 64."""
    side = min(shape[-2:])
    factors = [1]
    while side / (factors[-1] * 2) >= min_side and len(factors) < 4:
        factors.append(factors[-1] * 2)
    return tuple(reversed(factors))


# Under a time budget a coarse level may spend this share of what is left when it starts.
LEVEL_SHARE = 0.15


class CoarseToFine(MethodBase):
    """A `Method` (rngcam.recon.loop) that runs `make(level_problem, x0)` at each level in turn.

    A coarse level ends when its objective has fallen by less than `level_rtol` over its last
    `window` steps (`level_stop="objective"`; with "method": when the level's own `converged()`
    gives a reason, for methods with a stochastic objective), after `max_level_steps` steps, or
    when its steps have used their share (`level_share`) of what the run's `clock`
    (rngcam.recon.loop.Clock) had left when the level started (only time inside step()
    counts, not the loop's evaluations); the final level runs for as long as the loop lets it.
    A finer level is not started when what the clock has left looks too short for its set-up
    and `fine_steps` steps (8x the current level's, per halving): the run then ends on the
    current level, upsampled (plus `detail(full_problem, coarse_shape)`, the full grid's detail
    that level cannot hold, when given), and `budget_cut()` says so. `estimate()` is always on
    the full grid. `stage(message)` reports each level's set-up.
    """

    def __init__(self, problem: Problem, make: Callable[[Problem, Tensor | None], object],
                 factors: tuple[int, ...] | None = None, clock: Clock | None = None,
                 level_share: float = LEVEL_SHARE, level_rtol: float = 2e-3, window: int = 10,
                 max_level_steps: int = 300, stage: Callable[[str], None] | None = None,
                 level_stop: str = "objective", fine_steps: int = 5,
                 detail: Callable[[Problem, tuple[int, int, int, int]], Tensor] | None = None,
                 time_factors: tuple[int, ...] | None = None):
        self.full_shape = problem.shape
        self.factors = tuple(factors or default_factors(problem.shape))
        if self.factors[-1] != 1:
            self.factors = (*self.factors, 1)
        # frames a coarse frame bins, per level (default: the spatial factors)
        self.time_factors = tuple(time_factors or self.factors)
        if len(self.time_factors) != len(self.factors) or self.time_factors[-1] != 1:
            raise ValueError(f"time factors {self.time_factors} do not match the levels {self.factors}")
        self.problems = [coarsen(problem, f, t) if f > 1 or t > 1 else problem
                         for f, t in zip(self.factors, self.time_factors, strict=True)]
        self.make, self.clock, self.level_share = make, clock, level_share
        self.level_rtol, self.window, self.max_level_steps = level_rtol, window, max_level_steps
        self.level_stop, self.level_ends, self.fine_steps = level_stop, [], fine_steps
        self.detail, self._detail = detail, (None, None)  # (level, the full grid's detail for it)
        self.stage = stage or (lambda message: None)
        self.level, self._x0, self.held_back = 0, None, False
        self._start_level(0, None)
        self.name, self.stops_itself = self.method.name, self.method.stops_itself
        # a split of RS rows reaches every level (coarsen): the levels' methods fit only its training rows
        self.supports_holdout = bool(self.method.supports_holdout)

    # --- levels ---
    def _describe(self, i: int) -> str:
        c, k, h, w = self.problems[i].shape
        return f"level {i + 1} of {len(self.problems)} ({h}x{w}x{k})"

    def _start_level(self, i: int, x0: Tensor | None) -> None:
        self.stage(f"{self._describe(i)}: building")
        t0 = time.perf_counter()
        self.level, self._x0, self._detail = i, x0, (None, None)  # the coarser level's detail can go
        self.method = self.make(self.problems[i], x0)
        self.level_steps, self.level_step_s, self._history = 0, 0.0, []
        self.level_setup_s = time.perf_counter() - t0
        self.level_share_s = None if self.clock is None else self.clock.share(self.level_share)  # its steps' time
        self.stage(f"{self._describe(i)}: ready")

    def _level_done(self, objective: float) -> bool:
        self._history.append(objective)
        if self.level_steps >= self.max_level_steps:
            return True
        if self.level_share_s is not None and self.level_step_s >= self.level_share_s:
            return True
        if self.level_stop == "method":
            reason = self.method.converged()
            if reason:
                self.stage(f"{self._describe(self.level)}: {reason}")
            return bool(reason)
        if len(self._history) > self.window:
            old, new = self._history[-1 - self.window], self._history[-1]
            return math.isfinite(old) and abs(old - new) <= self.level_rtol * abs(old)
        return False

    def _next_level_fits(self) -> bool:
        left = None if self.clock is None else self.clock.left()
        if left is None:
            return True
        i = self.level
        growth = ((self.factors[i] / self.factors[i + 1]) ** 2 * self.time_factors[i] / self.time_factors[i + 1])
        per_step = self.level_step_s / max(self.level_steps, 1)
        # A level whose build is not the coarse one's (STFM: one fit instead of RIFE and an
        # ensemble) is guessed from its steps alone.
        setup = self.level_setup_s if self.level_stop == "objective" else 0.0
        needed = growth * (setup + self.fine_steps * per_step)
        return needed <= left

    def _next_level(self) -> None:
        self.level_ends.append({"level": self._describe(self.level), "steps": self.level_steps,
                                "step_s": round(self.level_step_s, 2), "setup_s": round(self.level_setup_s, 2)})
        i = self.level + 1
        fine = self.problems[i].shape
        # Half precision: the start is kept for a checkpoint's resume (the level is rebuilt from it)
        # and a level starts from exactly what a resume would rebuild it from.
        x0 = upsample(self.method.estimate().detach(), fine, self.time_factors[i - 1] / self.time_factors[i],
                      dtype=START_DTYPE)
        self.method = None  # make() may keep what it needs of the coarser level; the rest can go
        release_free_memory()
        self._start_level(i, x0)
        release_free_memory()  # what make() let go of the coarser level

    @property
    def final(self) -> bool:
        return self.level == len(self.problems) - 1

    def fit_every_row(self) -> bool:
        """The final level's fit fits the held-out RS rows too (where it can: stfm.floor); False elsewhere."""
        fit_all = getattr(self.method, "fit_every_row", None) if self.final else None
        return bool(fit_all()) if fit_all is not None else False

    @property
    def steps(self) -> int:
        """Steps taken so far, over every level."""
        return sum(int(end["steps"]) for end in self.level_ends) + self.level_steps

    # --- Method protocol ---
    def step(self) -> float:
        t0 = time.perf_counter()
        objective = float(self.method.step())
        self.level_steps += 1
        self.level_step_s += time.perf_counter() - t0
        if (not self.final and not self.held_back and math.isfinite(objective)
                and self._level_done(objective)):
            if self._next_level_fits():
                self._next_level()
            else:
                self.held_back = True
                self.stage(f"{self._describe(self.level)}: too little of the time budget left for the next "
                           f"level; staying here")
        return objective

    def estimate(self) -> Tensor:
        x = self.method.estimate()
        if self.final:
            return x
        up = upsample(x.detach(), self.full_shape, self.time_factors[self.level])
        if self.detail is None:
            return up
        if self._detail[0] != self.level:  # computed once per level, on the full grid
            self._detail = (None, None)
            self._detail = (self.level, self.detail(self.problems[-1], tuple(x.shape)).to(up))
        return up.add_(self._detail[1]).clamp_min_(0)

    def residuals(self) -> dict[str, float]:
        return self.method.residuals()  # of the current level's problem

    def converged(self) -> str | None:
        return self.method.converged() if self.final else None

    def log_ready(self) -> bool:
        return self.method.log_ready() if self.final else True  # coarse levels run no stop test

    def budget_cut(self) -> str:
        if self.final:
            return ""
        why = " (too little budget left to start the next)" if self.held_back else ""
        return (f"stopped at {self._describe(self.level)}{why}; levels {self.level + 2}-{len(self.problems)} "
                f"(the full grid last) not reached: the video is the coarse estimate upsampled")

    def state_dict(self) -> dict:
        return {"level": self.level, "level_steps": self.level_steps, "x0": Kept(self._x0),
                "method": self.method.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        if state["level"] != self.level:
            self._start_level(state["level"], kept(state["x0"]))
        self.level_steps = state["level_steps"]
        self.method.load_state_dict(state["method"])

    def reduce_step(self, factor: float) -> None:
        self.method.reduce_step(factor)

    def end_fit(self) -> None:
        self.method.end_fit()

    def resolved_settings(self) -> dict:
        """The current level's method's settings, and how each finished level went."""
        inner = self.method.resolved_settings() or {}
        now = {"level": self._describe(self.level), "steps": self.level_steps,
               "step_s": round(self.level_step_s, 2), "setup_s": round(self.level_setup_s, 2)}
        return {**inner, "levels": [*self.level_ends, now]}

    def gains(self):
        return self.method.gains()

    def line_factor(self) -> float | None:
        """The current level's learned RS line-time factor (None: it learns none)."""
        get = getattr(self.method, "line_factor", None)
        return get() if callable(get) else None

    def components(self) -> dict:
        """The method's components, upsampled to the full grid when the run ended on a coarser level
        (motion in pixels scaled with the grid)."""
        out = self.method.components()
        if self.final:
            return out
        _, k, h, w = self.full_shape
        f = self.factors[self.level]
        full = {}
        for name, a in out.items():
            x = torch.as_tensor(a, dtype=torch.float32)
            x = x[:, None] if x.ndim == 3 else x  # a still image: one frame
            x = upsample(x, (x.shape[0], k if x.shape[1] > 1 else 1, h, w), self.time_factors[self.level])
            full[name] = (x[:, 0] if np.ndim(a) == 3 else x * (f if name == "motion" else 1)).cpu().numpy()
        return full

    @property
    def left_out(self):
        return self.method.left_out

    @property
    def notes(self):
        return self.method.notes
