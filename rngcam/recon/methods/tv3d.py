"""3-D TV baseline (after Antipa et al., ICCP 2019): FISTA on the RS (+ GS) measurements.

Objective, with each data term scaled by its operator's squared norm so that psi is a relative
weight (the RS operator's norm is often ~40x below the GS one):

    F(v) = 1/2 ||A_G v - b_G||^2 / n_G + psi/2 ||A_R v - b_R||^2 / n_R + tau TV3_beta(v),  v >= 0

TV3_beta is anisotropic 3-D TV with temporal weight beta (rngcam.physics.tv_prox). Step 1/L with L the
squared norm of the scaled stacked operator (power iteration). With `gs_anchor="hard"` the GS
term leaves the objective and every iterate is projected onto {A_G v = b_G} after the prox, then
clipped at zero (a heuristic splitting, documented as such; the projection is exact per pixel).
With `restart=True` the iteration is monotone: a step that would raise F is rejected and the
momentum restarted (O'Donoghue & Candes 2015, with the MFISTA safeguard of Beck & Teboulle);
if the restarted step still raises F the step is too long and L is doubled until it does not
(backtracking). A non-finite objective is returned as is, for the loop's NaN guard.

With a held-out split on the problem (Problem.with_holdout) only the training measurements are
fitted: each data term becomes ||M (A v - b)||^2 with M the 0/1 mask, i.e. the operator M A
(adjoint A^T M, since M is diagonal and 0/1); ||M A|| <= ||A|| keeps the step valid. Hard
anchoring then projects onto the fitted GS pixels only. `residuals()` reports the training fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.memory import release_free_memory
from rngcam.physics import tv_prox as tv
from rngcam.physics.operators import LinearOperator
from rngcam.recon import ablation
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.baselines import blend
from rngcam.recon.methods.coarse_to_fine import CoarseToFine, Kept, default_factors, kept, power_norm, upsample
from rngcam.recon.methods.selfcal import calibrate_problem, report_lines
from rngcam.recon.metrics import relative_residual
from rngcam.recon.options import setting
from rngcam.recon.problem import Problem

_MAX_BACKTRACKS = 60  # 2^60: enough to recover from any step length a float can hold
_BACKTRACK_RTOL = 1e-9  # an approximate prox may raise F by rounding; don't backtrack for that


@dataclass
class TV3DSettings:
    tau: float = setting(2e-3, "weight of the video's 3-D TV against the data terms", unit="relative",
                         sweep=True)
    beta: float = setting(1.0, "weight of the TV along time relative to along x and y", unit="relative",
                          sweep=True)
    psi: float = setting(1.0, "RS data weight relative to GS (each term scaled by its operator's norm)",
                         unit="relative", sweep=True)
    prox: str = setting("haar", "the TV prox: haar (fast, Antipa et al.) or exact", choices=("haar", "exact"))
    gs_anchor: str = setting("soft", "GS frames as a loss term (soft) or a projection onto them (hard)",
                             choices=("soft", "hard"))
    restart: bool = True
    no_rs: bool = setting(False, "leave the RS measurement out of the fit")
    no_gs: bool = setting(False, "leave the GS frames out of the fit")
    init: str = "blend"  # "blend" (cross-fade of the GS frames) or "zeros"
    self_calibrate: str = setting("off", "refine the calibration from the RS rows exposed with the GS frames "
                                         "first (rngcam.recon.methods.selfcal): gains, all (and the GS-to-RS transform "
                                         "where the data pin it) or off", choices=("off", "gains", "all"))
    coarse_to_fine: bool = setting(True, "on grids of 96 px and more, reconstruct 1/4 and 1/2 grids first, "
                                         "each starting the next (else one level at the full grid)")

    def __post_init__(self):
        for name in ("tau", "beta", "psi"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0):
                raise ConfigError(f"tv3d: {name} must be finite and >= 0, got {val}")
        if self.prox not in ("exact", "haar"):
            raise ConfigError(f"tv3d: prox must be 'exact' or 'haar', got {self.prox!r}")
        if self.gs_anchor not in ("soft", "hard"):
            raise ConfigError(f"tv3d: gs_anchor must be 'soft' or 'hard', got {self.gs_anchor!r}")
        if self.self_calibrate not in ("off", "gains", "all"):
            raise ConfigError(f"tv3d: self_calibrate must be off, gains or all, got {self.self_calibrate!r}")


class _Scaled(LinearOperator):
    """The data terms as one operator: blocks c_i A_i with measurements c_i b_i."""

    def __init__(self, blocks: list[tuple[LinearOperator, float]], domain_shape):
        self.blocks, self.domain_shape = blocks, domain_shape

    def A(self, v):
        return tuple(c * op.A(v) for op, c in self.blocks)

    def A_adjoint(self, y):
        out = None  # accumulated in place: one video-sized temporary at a time
        for (op, c), yi in zip(self.blocks, y):
            out = op.A_adjoint(yi).mul_(c) if out is None else out.add_(op.A_adjoint(yi), alpha=c)
        return out


class _Masked(LinearOperator):
    """M A for a 0/1 mask M broadcast over A's output; the adjoint is A^T M."""

    def __init__(self, op: LinearOperator, mask: Tensor):
        self.op, self.mask, self.domain_shape = op, mask, op.domain_shape

    def A(self, v):
        return self.mask * self.op.A(v)

    def A_adjoint(self, y):
        return self.op.A_adjoint(self.mask * y)


def _product(a: Tensor | None, b: Tensor | None) -> Tensor | None:
    """The product of two optional 0/1 masks (None: all ones)."""
    return b if a is None else a if b is None else a * b


class TV3D(MethodBase):
    """FISTA for the 3-D TV objective above; a `Method` for rngcam.recon.loop."""

    name = "tv3d"
    supports_holdout = True  # fits only the training measurements when the problem has a split

    def __init__(self, problem: Problem, settings: TV3DSettings | None = None, x0: Tensor | None = None,
                 rs_norm_start: Tensor | None = None):
        """`x0`: a starting video (C, K, H, W) instead of `settings.init` (a coarser level's estimate);
        `rs_norm_start`: a start for the RS operator's power iteration (a coarser level's
        `rs_norm_vector`, upsampled)."""
        self.p, self.s, self._x0 = problem, settings or TV3DSettings(), x0
        self.notes = ablation.selfcal_note(self.s)
        self.rs_norm_vector = None
        use_rs = not self.s.no_rs and problem.b_rs is not None
        use_gs = not self.s.no_gs and problem.b_gs is not None and problem.b_gs.shape[1] > 0
        if not (use_rs or use_gs):
            raise ConfigError("tv3d needs RS or GS measurements; the problem has neither in use")
        problem.check_finite("tv3d")
        self.rs = problem.rs_op() if use_rs else None
        self.gs = problem.gs_op() if use_gs else None
        self.hard = use_gs and self.s.gs_anchor == "hard"
        first = problem.b_rs if use_rs else problem.b_gs
        dev, dt = first.device, first.dtype
        # The operators and measurements that are fitted: all, or the training split.
        self.rs_fit, self.b_rs_fit = self.rs, problem.b_rs
        self.gs_fit, self.b_gs_fit = self.gs, problem.b_gs
        # ... and only the pixels that carry linear information (saturated ones do not).
        rs_m = _product(problem.rs_fit_mask(), problem.rs_valid_mask())
        gs_m = _product(problem.gs_fit_mask(), problem.gs_valid_mask())
        if use_rs and rs_m is not None:
            m = rs_m.to(dtype=dt, device=dev)
            self.rs_fit, self.b_rs_fit = _Masked(self.rs, m), m * problem.b_rs
        self._anchor_mask = None
        if use_gs and gs_m is not None:
            m = gs_m.to(dtype=dt, device=dev)
            self.gs_fit, self.b_gs_fit = _Masked(self.gs, m), m * problem.b_gs
            self._anchor_mask = m.amin(0).expand(problem.b_gs.shape[1:])  # (G, H, W): every channel fitted
        blocks, meas, norms_sq = [], [], []
        if use_rs and self.s.psi > 0 or (use_rs and not use_gs):
            # Power iteration underestimates; a 2 % margin keeps the step safe.
            if rs_norm_start is None:
                n_r = 1.02 * self.rs.norm(iters=20, tol=1e-3, dtype=dt, device=dev) ** 2
            else:
                norm, self.rs_norm_vector = power_norm(self.rs, rs_norm_start.to(dtype=dt, device=dev))
                n_r = 1.02 * norm ** 2
            c = math.sqrt((self.s.psi if use_gs else 1.0) / max(n_r, 1e-30))
            blocks.append((self.rs_fit, c))
            meas.append(c * self.b_rs_fit)
            norms_sq.append(n_r)
        if use_gs and not self.hard:
            n_g = self.gs.norm() ** 2
            c = math.sqrt(1.0 / max(n_g, 1e-30))
            blocks.append((self.gs_fit, c))
            meas.append(c * self.b_gs_fit)
            norms_sq.append(n_g)
        self.op = _Scaled(blocks, problem.shape)
        self.b = tuple(meas)
        # Each block has norm c_i ||A_i|| = sqrt(weight_i), so L <= sum of the weights (a valid step).
        self.L = max(sum(c * c * n for (_, c), n in zip(blocks, norms_sq)), 1e-12)
        if self.hard:
            w = self.gs.weights.to(dtype=dt, device=dev)
            self._gram_inv_w = torch.linalg.pinv(w @ w.T) @ w  # (G, K): projection onto A_G v = b_G
            if self._anchor_mask is not None:
                self._anchor_patterns = self._masked_projections(w, self._anchor_mask)
        x0 = self._initial(dt, dev)
        ax0 = self.op.A(x0)
        self.state = {"x": x0, "Ax": ax0, "y": x0, "Ay": ax0, "t": 1.0, "L": self.L,
                      "F": self._objective(x0, ax0), "restarts": 0}

    # The state's videos are replaced by every step, never changed in place, so a copy of the state
    # (the loop's last good state) may share them (coarse_to_fine.Kept) instead of copying videos.
    _VIDEOS = ("x", "y")

    def _initial(self, dtype, device) -> Tensor:
        p = self.p
        if self._x0 is not None:
            x = self._x0.to(dtype=dtype, device=device, copy=True).clamp_min_(0)
            self._x0 = None  # not kept: the state holds it
        elif self.s.init == "blend" and p.b_gs is not None and p.b_gs.shape[1] > 0:
            frames = p.gs_images()  # held-out GS pixels are filled from fitted ones: no leak
            x = torch.from_numpy(blend(frames.cpu().float().numpy(), p.gs_times_s, p.frame_times_s))
            x = x.to(dtype=dtype, device=device).clamp_min(0)
        else:
            x = torch.zeros(p.shape, dtype=dtype, device=device)
        return self._project(x)

    @staticmethod
    def _masked_projections(w: Tensor, mask: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Per pattern of fitted key frames at a pixel: (pixels (H, W) bool, pinv(M W)^T (G, K))."""
        mask = mask.expand(w.shape[0], *mask.shape[-2:]).bool()  # (G, H, W)
        code = sum(mask[g].long() << g for g in range(mask.shape[0]))
        out = []
        for c in torch.unique(code).tolist():
            m = torch.tensor([(c >> g) & 1 for g in range(w.shape[0])], dtype=w.dtype, device=w.device)
            out.append((code == c, torch.linalg.pinv(m[:, None] * w).T))
        return out

    def _project(self, x: Tensor) -> Tensor:
        if not self.hard:
            return x
        r = self.b_gs_fit - self.gs_fit.A(x)  # (C, G, H, W), zero where held out
        if self._anchor_mask is None:
            x = x + torch.einsum("cghw,gk->ckhw", r, self._gram_inv_w)
        else:  # the projection onto the fitted rows of W differs with the pattern of fitted frames
            x = x.clone()
            for pixels, proj in self._anchor_patterns:
                x[:, :, pixels] += torch.einsum("cgn,gk->ckn", r[:, :, pixels], proj)
        return x.clamp_min(0)

    def objective(self, x: Tensor) -> float:
        return self._objective(x, self.op.A(x))

    def _objective(self, x: Tensor, ax: tuple) -> float:
        """F(x) given the scaled measurements' prediction ax = op.A(x)."""
        data = 0.5 * sum(float(((a - b) ** 2).sum()) for a, b in zip(ax, self.b))
        # channel by channel (TV never couples channels): temporaries of one channel, not the video
        return data + self.s.tau * sum(float(tv.tv3(x[c:c + 1], self.s.beta)) for c in range(x.shape[0]))

    def _prox_grad(self, y: Tensor, ay: tuple, L: float) -> Tensor:
        if self.op.blocks:  # y - A^T(A y - b) / L, in the adjoint's own new tensor
            y = self.op.A_adjoint(tuple(a - b for a, b in zip(ay, self.b))).div_(-L).add_(y)
        if not bool(torch.isfinite(y).all()):
            return y  # diverged: the loop's NaN guard rolls back (the prox refuses NaN/Inf)
        z = torch.empty_like(y)
        for c in range(y.shape[0]):  # channels never interact: the prox's temporaries are one channel's
            z[c:c + 1] = tv.prox_tv_nonneg(y[c:c + 1], self.s.tau / L, self.s.beta, method=self.s.prox)
        del y
        return self._project(z)

    def _try(self, y: Tensor, ay: tuple, L: float) -> tuple[Tensor, tuple, float]:
        z = self._prox_grad(y, ay, L)
        az = self.op.A(z)
        return z, az, self._objective(z, az)

    def step(self) -> float:
        # A is linear, so A(y) for the extrapolated point comes from the cached A(x) and A(z):
        # one forward and one adjoint per iteration, not two forwards.
        st = self.state
        z, az, f_z = self._try(st["y"], st["Ay"], st["L"])
        if not math.isfinite(f_z):
            return f_z  # overflow or NaN: the loop's guard rolls back and halves the step
        if self.s.restart and f_z > st["F"]:
            # Reject the step and restart momentum from the current iterate; if even that step
            # raises F, the step is too long: backtrack (double L) until it does not.
            st["restarts"] += 1
            st["t"], st["y"], st["Ay"] = 1.0, st["x"], st["Ax"]
            for _ in range(_MAX_BACKTRACKS + 1):
                z, az, f_z = self._try(st["y"], st["Ay"], st["L"])
                if math.isfinite(f_z) and f_z <= st["F"] * (1 + _BACKTRACK_RTOL):
                    break
                st["L"] *= 2.0
            else:
                return st["F"]  # no decrease at any step length: keep x
            if f_z > st["F"]:
                return st["F"]  # the (approximate) prox made no progress; keep x
        t_new = (1 + math.sqrt(1 + 4 * st["t"] ** 2)) / 2
        momentum = (st["t"] - 1) / t_new
        st["y"] = None  # the old extrapolated point goes before the new one is made
        st["y"] = torch.sub(z, st["x"]).mul_(momentum).add_(z)
        st["Ay"] = tuple(a + momentum * (a - b) for a, b in zip(az, st["Ax"]))
        st["x"], st["Ax"], st["t"], st["F"] = z, az, t_new, f_z
        return f_z

    def estimate(self) -> Tensor:
        return self.state["x"]

    def residuals(self) -> dict[str, float]:
        x, out = self.state["x"], {}
        if self.rs is not None:
            out["rs"] = relative_residual(self.rs_fit.A(x), self.b_rs_fit)
        if self.gs is not None:
            out["gs"] = relative_residual(self.gs_fit.A(x), self.b_gs_fit)
        return out

    def state_dict(self) -> dict:
        return {k: Kept(v) if k in self._VIDEOS else v for k, v in self.state.items()}

    def load_state_dict(self, state: dict) -> None:
        self.state = {k: kept(v) for k, v in state.items()}

    def reduce_step(self, factor: float) -> None:
        self.state["L"] /= factor
        self.state["t"], self.state["y"], self.state["Ay"] = 1.0, self.state["x"], self.state["Ax"]


def make_tv3d(problem: Problem, settings: TV3DSettings | None = None, clock=None,
              stage=None):
    """TV3D on `problem`, coarse-to-fine (rngcam.recon.methods.coarse_to_fine) when the grid is large enough,
    the setting is on and no held-out split is fitted; `stage(message)` reports set-up stages.
    With `self_calibrate`, the problem's GS frames are first corrected (rngcam.recon.methods.selfcal) and
    the refined values are in the method's notes and `selfcal_report`. With `no_rs` / `no_gs` the
    runner hands it the problem without that camera (rngcam.recon.runner.method_view) and self-calibration is off."""
    settings = settings or TV3DSettings()
    calibrate = settings.self_calibrate != "off" and not ablation.removed(settings)
    method = _make_tv3d(problem, settings, clock, stage) if not calibrate else None
    if method is None:
        problem, report = calibrate_problem(problem, settings.self_calibrate)
        method = _make_tv3d(problem, settings, clock, stage)
        method.selfcal_report = report
        try:
            method.notes = list(method.notes) + report_lines(report)
        except AttributeError:  # coarse to fine: its notes are its last level's (selfcal_report has all)
            pass
    return method


def _make_tv3d(problem: Problem, settings: TV3DSettings, clock, stage):
    factors = default_factors(problem.shape)
    if not settings.coarse_to_fine or len(factors) == 1 or problem.has_holdout:
        if stage:
            stage(f"tv3d on {problem.shape[-2]}x{problem.shape[-1]}x{problem.shape[1]}: operator norms")
        return TV3D(problem, settings)

    previous: list[TV3D] = []

    def make(level: Problem, x0):
        start = None
        if previous and previous[-1].rs_norm_vector is not None:
            coarse = previous[-1].rs_norm_vector.float()
            start = upsample(coarse, level.shape, level.shape[1] / coarse.shape[1])
        elif level.b_rs is not None:  # the coarsest level: a seeded random start, kept for the next
            gen = torch.Generator().manual_seed(0)
            start = torch.randn(level.shape, generator=gen, dtype=torch.float64)
        previous.clear()  # the coarser level goes before this one is built
        release_free_memory()
        method = TV3D(level, settings, x0=x0, rs_norm_start=start)
        # Only a finer level needs the power iteration's vector (a warm start: half precision will do).
        final = level.shape == problem.shape
        method.rs_norm_vector = None if final or method.rs_norm_vector is None else method.rs_norm_vector.half()
        previous[:] = [method]
        return method

    return CoarseToFine(problem, make, factors, clock=clock, stage=stage)
