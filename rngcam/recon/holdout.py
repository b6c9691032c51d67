"""Held-out measurement validation: score a reconstruction on measurements it was not fitted to.

The split lives on the Problem (`Problem.with_holdout`: held-out RS row bins and, optionally, GS
pixels). A method fitted on the training part predicts the held-out part through the same
operators; the relative residual there measures how well settings (beta, tau, psi) generalise,
with no truth.

    heldout_rs = ||M_R (A_R v - b_R)|| / ||M_R b_R||      (M_R: held-out RS rows)
    heldout_gs = ||M_G (A_G v - b_G)|| / ||M_G b_G||      (M_G: held-out GS pixels)
    heldout    = sqrt( sum_s ||M_s (A_s v - b_s)||^2 / n_s  /  sum_s ||M_s b_s||^2 / n_s )

over the sensors with a split, with n_s = ||A_s||^2: the operator-norm balance of the fit
objectives at psi = 1 (the RS operator's norm is often ~40x below the GS one, so plain sums
would ignore the RS image). The combined score does not depend on psi. With only RS rows held
out (the default split) `heldout` equals `heldout_rs`.

Why RS rows by default: held-out RS rows are exposures at times between the key frames, which
is what the reconstruction has to get right; they are held out in blocks one exposure long, so
a block is not just the average of its fitted neighbours (Problem.with_holdout). Measured with
tv3d on 4x3 beta/tau grids (2 cores, 100 iterations):
- moving square, caustic PSF, 16 px, 0.2 of the rows held out, 5 split seeds: Spearman(score,
  true PSNR) 0.75-0.82 with two folds, 0.85-0.96 with three (hence the sweep's default); the
  pick within 0.3 dB of the best. Isolated held-out GS pixels (a spatial inpainting test that
  rewards heavy smoothing) ranked against the PSNR (-0.5 to -0.2).
- smoke scene (rngcam simulate), 32 px: 0.39, best setting picked; 64 px, two folds: -0.28,
  the pick 0.65 dB below the best. There the PSNR rewards a nearly static video (beta 100),
  while the RS rows, seen through a PSF with <1 % of its frequencies above 10 % of DC, favour
  the video that explains them (beta 10): a measurement-domain score cannot see what the
  operators do not measure. Holding out the middle key frame ranked at 0.51 on the 32 px
  smoke scene (not offered yet).
"""

from __future__ import annotations

import math

from torch import Tensor

from rngcam.recon.problem import Problem

HELDOUT_KEYS = ("heldout", "heldout_rs", "heldout_gs")


class HoldoutScorer:
    """Scores videos on a problem's held-out measurements; operator norms are computed once."""

    def __init__(self, problem: Problem):
        if not problem.has_holdout:
            raise ValueError("the problem has no held-out split (use Problem.with_holdout)")
        self.p = problem
        self._terms = []  # (name, op, heldout mask, measurement, squared operator norm)
        if problem.b_rs is not None and problem.rs_train_rows is not None:
            op = problem.rs_op()
            n = op.norm(iters=20, tol=1e-3, dtype=problem.b_rs.dtype, device=problem.b_rs.device) ** 2
            self._terms.append(("rs", op, problem.rs_fit_mask(heldout=True), problem.b_rs, n))
        if problem.b_gs is not None and problem.gs_train_mask is not None:
            op = problem.gs_op()
            self._terms.append(("gs", op, problem.gs_fit_mask(heldout=True), problem.b_gs, op.norm() ** 2))

    def __call__(self, video: Tensor) -> dict[str, float]:
        """{"heldout_rs", "heldout_gs" (those with a split), "heldout"}; relative residuals."""
        out, num, den = {}, 0.0, 0.0
        for name, op, mask, b, n in self._terms:
            v = video.to(dtype=b.dtype, device=b.device)
            m = mask.to(dtype=b.dtype, device=b.device)
            r_sq = float((m * (op.A(v) - b)).double().square().sum())
            b_sq = float((m * b).double().square().sum())
            out[f"heldout_{name}"] = _ratio(r_sq, b_sq)
            num += r_sq / max(n, 1e-30)
            den += b_sq / max(n, 1e-30)
        out["heldout"] = _ratio(num, den)
        # A diverged video (NaN) scores as the worst possible, never as a silent NaN.
        return {k: (v if not math.isnan(v) else math.inf) for k, v in out.items()}


def _ratio(num_sq: float, den_sq: float) -> float:
    if den_sq == 0:
        return 0.0 if num_sq == 0 else math.inf
    return math.sqrt(num_sq / den_sq)


def holdout_residuals(problem: Problem, video: Tensor) -> dict[str, float]:
    """Relative residuals of `video` (C, K, H, W) on the problem's held-out measurements only:
    {"heldout_rs", "heldout_gs", "heldout" (combined, see the module docstring)}."""
    return HoldoutScorer(problem)(video)
