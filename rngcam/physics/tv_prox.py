"""Proximal operators of anisotropic 3-D total variation: the FISTA-3DTV baseline (recon.methods.tv3d),
plug-and-play's 2-D fallback (recon.methods.pnp) and the RS deconvolution of calibration (calibrate.deconv).

Convention (every function in this module uses it)
--------------------------------------------------
A video ``v`` has shape (C, T, H, W). With forward differences and no wrap-around,

    TV3_beta(u) = sum |D_x u| + sum |D_y u| + beta_t * sum |D_t u|

where D_x, D_y, D_t difference neighbouring samples along W, H and T, and the sums run over
all channels (channels never interact). The proximal operator is

    prox_tv(v, lam, beta_t) = argmin_u  1/2 ||u - v||^2 + lam * TV3_beta(u)

so a FISTA step on 1/2 ||A v - b||^2 + tau * TV3_beta(v) with step 1/L uses ``lam = tau / L``.
``lam`` and ``beta_t`` are plain non-negative numbers.

Three operators share that convention:

* ``prox_tv_exact``: the true prox, by accelerated block ascent on the dual with one block per
  axis, each block step solved exactly by the 1-D solver ``tv1d_exact`` (Condat's direct
  algorithm); it stops on a certified duality-gap bound on the error.
* ``prox_tv_haar``: the fast one-shot approximation of Kamilov (2016) used by Antipa et al.
  (2019): cycle-spun single-level Haar shrinkage along each axis, averaged.
* ``prox_tv_nonneg``: either of them followed by ``nonneg`` (clamp at zero). For the exact prox
  this composition IS the prox of lam * TV3_beta + indicator(u >= 0), in any dimension (see its
  docstring); for the Haar approximation it is the clamp of the approximation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from rngcam.errors import ConfigError, RngcamError

# Video axes (C, T, H, W): the temporal axis carries weight beta_t, the spatial ones weight 1.
_T_DIM, _Y_DIM, _X_DIM = 1, 2, 3


# --------------------------------------------------------------------------- validation


def _check_weight(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or value < 0:
        raise ConfigError(f"{name} must be a finite number >= 0, got {value}")
    return value


def _check_video(v: Tensor) -> None:
    if not isinstance(v, Tensor) or v.ndim != 4:
        shape = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
        raise ConfigError(f"TV prox expects a video tensor of shape (C, T, H, W), got {shape}")
    if not v.is_floating_point():
        raise ConfigError(f"TV prox expects a floating-point video, got {v.dtype}")
    if not bool(torch.isfinite(v).all()):
        raise RngcamError("TV prox got a video with NaN or infinite values")


def _axis_weights(beta_t: float) -> tuple[tuple[int, float], ...]:
    return ((_X_DIM, 1.0), (_Y_DIM, 1.0), (_T_DIM, beta_t))


# --------------------------------------------------------------------------- TV value and gradient


def tv3(v: Tensor, beta_t: float) -> Tensor:
    """TV3_beta(v) of a (C, T, H, W) video, summed over channels (0-d tensor)."""
    beta_t = _check_weight("beta_t", beta_t)
    spatial = (v.diff(dim=_X_DIM).abs().sum() + v.diff(dim=_Y_DIM).abs().sum())
    if beta_t == 0:
        return spatial
    return spatial + beta_t * v.diff(dim=_T_DIM).abs().sum()


def grad3(v: Tensor) -> Tensor:
    """Forward differences (D_t, D_y, D_x) of a (C, T, H, W) video: shape (3, C, T, H, W).

    The last sample along each axis has no forward neighbour; its difference is 0.
    """
    g = v.new_zeros((3, *v.shape))
    for i, dim in enumerate((_T_DIM, _Y_DIM, _X_DIM)):
        g[i].narrow(dim, 0, v.shape[dim] - 1).copy_(v.diff(dim=dim))
    return g


def div3(g: Tensor) -> Tensor:
    """Discrete divergence, the negative adjoint of ``grad3``: <grad3 u, g> = -<u, div3 g>."""
    out = torch.zeros_like(g[0])
    for i, dim in enumerate((_T_DIM, _Y_DIM, _X_DIM)):
        n = g.shape[dim + 1]
        if n < 2:
            continue
        p = g[i].narrow(dim, 0, n - 1)  # the padded last difference is not a real one
        # (D^T p)_j = p_{j-1} - p_j, and div = -D^T.
        out.narrow(dim, 0, n - 1).add_(p)
        out.narrow(dim, 1, n - 1).sub_(p)
    return out


def nonneg(v: Tensor) -> Tensor:
    """Projection onto the non-negative orthant (elementwise max(v, 0))."""
    return v.clamp(min=0)


# --------------------------------------------------------------------------- exact 1-D TV


def tv1d_exact(x: Tensor, lam: float | Tensor) -> Tensor:
    """Exact 1-D TV denoising along the last axis: argmin_u 1/2||u - x||^2 + lam sum|u[i+1]-u[i]|.

    ``x`` has any leading (batch) shape; ``lam`` is a number or a tensor broadcastable to
    ``x.shape[:-1]`` (one weight per signal). Condat's direct algorithm (IEEE SPL 2013), run as
    a vectorised state machine over the batch, in float64; the result has ``x``'s dtype. A row
    whose lam exceeds max_j |cumsum(x - mean)_j| has the constant mean as its exact solution
    and is answered directly, which also keeps huge lam (1e12 and beyond) exact and finite.
    """
    if not isinstance(x, Tensor) or x.ndim < 1 or not x.is_floating_point():
        raise ConfigError("tv1d_exact expects a floating-point tensor with at least one axis")
    n = x.shape[-1]
    lam_t = torch.as_tensor(lam, dtype=torch.float64, device=x.device)
    if bool(torch.isnan(lam_t).any()) or bool((lam_t < 0).any()):
        raise ConfigError("tv1d_exact: lam must be >= 0")
    if n < 2 or x.numel() == 0:
        return x.clone()
    rows = x.reshape(-1, n).to(torch.float64)
    lam_rows = torch.broadcast_to(lam_t, x.shape[:-1]).reshape(-1)

    mean = rows.mean(dim=1, keepdim=True)
    centred = rows - mean
    lam_flat = centred.cumsum(dim=1)[:, :-1].abs().amax(dim=1)
    out = rows.clone()  # rows with lam = 0 stay exactly as given
    flat = lam_rows >= lam_flat
    out[flat] = mean.expand_as(rows)[flat]
    todo = (~flat & (lam_rows > 0)).nonzero().squeeze(1)
    if todo.numel():
        out[todo] = _condat_rows(centred[todo], lam_rows[todo]) + mean[todo]
    return out.to(x.dtype).reshape(x.shape)


def _condat_rows(x: Tensor, lam: Tensor) -> Tensor:
    """Condat's direct 1-D TV algorithm on every row of ``x`` (B, n) at once (lam: (B,)).

    Each row runs the paper's loop; one pass of the Python loop advances every unfinished row
    by one step: a sample advance, a jump (the current segment ends, scanning restarts after
    it), or a right-boundary step. A segment that ends is recorded by its value at its first
    index; forward filling then spreads the values over the segments, which tile the row in
    order. A row that has not ended writes its current value at its current segment start,
    which the segment's real value overwrites later; finished rows write to a scratch column
    until they are dropped (every few steps), so the cost follows the average row.

    Speed (CPU): the branch selections are blends ``torch.lerp(a, b, mask)`` with 0/1 float
    masks, several times faster than ``torch.where``; with weight exactly 0 or 1 ATen's lerp
    returns ``a`` or ``b`` exactly. The sample positions (k, k0, k-, k+) are small integers
    held exactly in the float dtype for the same reason.
    """
    b, n = x.shape
    dev, dt = x.device, x.dtype
    # Column-major: sample j of row r sits at j*b + r, so rows scanning similar positions touch
    # neighbouring memory (several times faster than row-major gathers and scatters on CPU).
    x_flat = x.t().reshape(-1)
    seg_value = x.new_full(((n + 1) * b,), math.nan)  # index j = n is the scratch slot
    last = float(n - 1)

    row = torch.arange(b, device=dev, dtype=dt)  # original row of each live state
    lam = lam.clone()
    k, k0, kminus, kplus = (torch.zeros(b, device=dev, dtype=dt) for _ in range(4))
    vmin, vmax = x[:, 0] - lam, x[:, 0] + lam
    umin, umax = lam.clone(), -lam
    done = torch.zeros(b, device=dev, dtype=dt)
    scratch = torch.full((b,), float(n), device=dev, dtype=dt)
    live_at_compaction = b

    def blend(a: Tensor, b_: Tensor, mask: Tensor) -> Tensor:
        return torch.lerp(a, b_, mask)

    max_steps = n * (n + 3) + 8  # every step grows k0 or k, and k0 never shrinks: O(n^2)
    for step in range(max_steps):
        at_end = k == last
        x_next = x_flat.index_select(0, ((k + 1).clamp(max=last) * b + row).long())
        umin_try = umin + x_next - vmin
        umax_try = umax + x_next - vmax
        neg_b = (umin_try < -lam) & ~at_end  # interior: the segment must step down
        pos_b = (umax_try > lam) & ~at_end & ~neg_b  # interior: the segment must step up
        end_neg_b = at_end & (umin < 0)
        end_pos_b = at_end & (umax > 0) & ~end_neg_b
        finish_b = at_end & ~end_neg_b & ~end_pos_b
        neg, pos, end_neg, end_pos = (m.to(dt) for m in (neg_b, pos_b, end_neg_b, end_pos_b))
        down, up = neg + end_neg, pos + end_pos
        jump = down + up
        advance = (~(at_end | neg_b | pos_b)).to(dt)

        value = blend(blend(vmin + umin / (k - k0 + 1), vmax, up), vmin, down)
        column = blend(k0, scratch, done) * b + row
        seg_value.put_(column.long(), value)

        new_k0 = blend(blend(k0, kplus + 1, up), kminus + 1, down)
        x_k0 = x_flat.index_select(0, (new_k0.clamp(max=last) * b + row).long())

        # Advance: the bounds tighten when the dual variable hits +-lam (paper's vmin/vmax update).
        k_adv = k + 1
        inv_len = 1.0 / (k_adv - k0 + 1)
        vmin_adv = vmin + (umin_try - lam).clamp(min=0) * inv_len
        vmax_adv = vmax + (umax_try + lam).clamp(max=0) * inv_len
        kminus_adv = blend(kminus, k_adv, (umin_try >= lam).to(dt))
        kplus_adv = blend(kplus, k_adv, (umax_try <= -lam).to(dt))

        resets_min = neg + pos + end_neg  # states whose umin restarts at lam
        resets_max = neg + pos + end_pos
        new_vmin = blend(blend(blend(vmin, vmin_adv, advance), x_k0 - 2 * lam, pos), x_k0, down)
        new_vmax = blend(blend(blend(vmax, vmax_adv, advance), x_k0 + 2 * lam, neg), x_k0, up)
        umin = blend(blend(umin_try.clamp(max=lam), x_k0 - lam - vmin, end_pos), lam, resets_min)
        umax = blend(blend(umax_try.clamp(min=-lam), x_k0 + lam - vmax, end_neg), -lam, resets_max)
        vmin, vmax = new_vmin, new_vmax
        kminus = blend(kminus_adv, new_k0, resets_min)
        kplus = blend(kplus_adv, new_k0, resets_max)
        k = blend(k_adv, new_k0, jump)
        k0 = new_k0

        done = torch.maximum(done, finish_b.to(dt))
        n_live = done.numel() - int(done.sum())
        if n_live == 0:
            break
        if n_live < 0.8 * live_at_compaction or (n_live < done.numel() and step % 16 == 15):
            keep = (done == 0).nonzero().squeeze(1)
            row, lam, k, k0, kminus, kplus = (t[keep] for t in (row, lam, k, k0, kminus, kplus))
            vmin, vmax, umin, umax, done = (t[keep] for t in (vmin, vmax, umin, umax, done))
            scratch = scratch[keep]
            live_at_compaction = n_live
    else:  # pragma: no cover - the algorithm terminates; this guards a float pathology
        raise RngcamError("tv1d_exact: Condat's algorithm did not terminate")

    seg_value = seg_value.view(n + 1, b)[:n].t()
    index = torch.arange(n, device=dev).expand(b, n)
    last_start = torch.where(seg_value.isnan(), 0, index).cummax(dim=1).values
    return seg_value.gather(1, last_start)


def _tv1d_along(v: Tensor, lam: float, dim: int) -> Tensor:
    moved = v.movedim(dim, -1)
    return tv1d_exact(moved.contiguous(), lam).movedim(-1, dim)


# --------------------------------------------------------------------------- exact 3-D prox


@dataclass(frozen=True)
class ProxInfo:
    """How ``prox_tv_exact`` ended: iterations run, and the certified bound on ||u - prox(v)||."""

    iterations: int
    error_bound: float
    converged: bool


def prox_tv_exact(
    v: Tensor,
    lam: float,
    beta_t: float,
    iters: int = 300,
    tol: float = 1e-5,
    check_every: int = 5,
    return_info: bool = False,
) -> Tensor | tuple[Tensor, ProxInfo]:
    """The exact prox of lam * TV3_beta (module docstring) of a (C, T, H, W) video.

    Dual problem: u = v - sum_a y_a with one dual field y_a per axis (x, y, t), each confined to
    {D_a^T p : |p| <= lam w_a}. The temporal block (the stiffest when beta_t is large) is
    minimised out exactly; FISTA with adaptive (gradient) restart runs on the remaining blocks
    (Lipschitz constant = their number; Chambolle & Pock 2015, "accelerated block-coordinate
    descent for proximity operators of sums"). Every block step is an exact 1-D prox
    (``tv1d_exact``), so beta_t = 1e6 or lam = 1e12 give exact means. All y_a stay
    dual-feasible, so the duality gap G = lam TV3(u) - <u, v - u> certifies the result:
    ||u - prox(v)|| <= sqrt(2 G). Every ``check_every`` iterations the gap is evaluated; the
    solver stops when sqrt(2 G) <= tol * ||v - mean(v)|| (per-channel means removed first: the
    prox commutes with adding a constant per channel) or after ``iters`` iterations. The gap is
    a difference of O(||v||^2) terms, so tol below ~1e-7 cannot be certified and runs to
    ``iters``. Computes in float64; returns ``v``'s dtype, and a ``ProxInfo`` when
    ``return_info``. Cost: 3 exact 1-D passes per iteration (~0.25 s CPU each at 3x64x64x64).
    """
    _check_video(v)
    lam = _check_weight("lam", lam)
    beta_t = _check_weight("beta_t", beta_t)
    if iters < 1 or check_every < 1:
        raise ConfigError("prox_tv_exact: iters and check_every must be >= 1")
    if not tol > 0:
        raise ConfigError(f"prox_tv_exact: tol must be > 0, got {tol}")
    blocks = [(d, lam * w) for d, w in _axis_weights(beta_t) if v.shape[d] > 1 and lam * w > 0]
    v64 = v.to(torch.float64)
    channel_mean = v64.mean(dim=(1, 2, 3), keepdim=True)
    v0 = v64 - channel_mean
    scale = float(v0.square().sum().sqrt())
    if not blocks or scale == 0.0:
        result = v.clone()
        return (result, ProxInfo(0, 0.0, True)) if return_info else result

    flat = _flat_solution(v0, blocks)
    if flat is not None:
        result = (flat + channel_mean).to(v.dtype)
        return (result, ProxInfo(0, 0.0, True)) if return_info else result

    (elim_dim, elim_lam), free = blocks[-1], blocks[:-1]  # the temporal block, if any, is last

    def primal(dual_sum: Tensor) -> Tensor:  # the exact minimiser over the eliminated block
        return _tv1d_along(v0 - dual_sum, elim_lam, elim_dim)

    if not free:  # a single block is solved exactly
        result = (primal(torch.zeros_like(v0)) + channel_mean).to(v.dtype)
        return (result, ProxInfo(1, 0.0, True)) if return_info else result

    lipschitz = float(len(free))
    duals = [torch.zeros_like(v0) for _ in free]
    ahead = [d.clone() for d in duals]  # FISTA's extrapolated point
    momentum = 1.0
    u, bound, iteration = v0, math.inf, 0
    for iteration in range(1, iters + 1):
        u_ahead = primal(sum(ahead))  # minus the gradient of the reduced dual at `ahead`
        new = []
        for (dim, weight), z in zip(free, ahead, strict=True):
            w = z + u_ahead / lipschitz
            # prox of (1/L) times the conjugate of weight*TV_a, by Moreau: w - prox_{L g}(L w) / L
            new.append(w - _tv1d_along(lipschitz * w, lipschitz * weight, dim) / lipschitz)
        restart = sum(float(((z - y) * (y - old)).sum())
                      for z, y, old in zip(ahead, new, duals, strict=True)) > 0
        next_momentum = 1.0 if restart else (1 + math.sqrt(1 + 4 * momentum**2)) / 2
        pull = 0.0 if restart else (momentum - 1) / next_momentum
        ahead = [y + pull * (y - old) for y, old in zip(new, duals, strict=True)]
        duals, momentum = new, next_momentum
        if iteration % check_every == 0 or iteration == iters:
            u = primal(sum(duals))
            gap = lam * float(tv3(u, beta_t)) - float((u * (v0 - u)).sum())
            bound = math.sqrt(2.0 * max(gap, 0.0))
            if bound <= tol * scale:
                break
    result = (u + channel_mean).to(v.dtype)
    if return_info:
        return result, ProxInfo(iteration, bound, bound <= tol * scale)
    return result


def _flat_solution(v0: Tensor, blocks: list[tuple[int, float]]) -> Tensor | None:
    """The prox when lam is so large that u is constant along every coupled axis, else None.

    Candidate: the mean of v0 over the coupled axes. It is the prox iff a dual p with
    D^T p = v0 - candidate and |p_a| <= lam w_a exists; one is built axis by axis (a running sum
    of the residual along x, then of the x-means along y, then along t). This answers huge lam
    exactly and at once, where the iterative gap would drown in rounding (lam * TV of ~1e-17).
    """
    r = v0
    for dim, weight in blocks:
        mean = r.mean(dim=dim, keepdim=True)
        dual = (r - mean).cumsum(dim=dim).narrow(dim, 0, r.shape[dim] - 1)
        if float(dual.abs().max()) > weight:
            return None
        r = mean
    return r.expand_as(v0).clone()


# --------------------------------------------------------------------------- Haar approximation


def prox_tv_haar(
    v: Tensor, lam: float, beta_t: float, shifts: Sequence[int] = (0, 1)
) -> Tensor:
    """Fast approximation of prox_tv (module convention): cycle-spun single-level Haar shrinkage.

    Along an axis with weight w, shift s pairs samples (s+2k, s+2k+1); the sum over shifts 0
    and 1 of w * sum_k |u[s+2k+1] - u[s+2k]| is that axis's TV, so
    TV3_beta = sum of K terms f_(axis,s). Each term has an exact prox: in the orthonormal Haar
    basis of its pairs, with detail d = (u1 - u0)/sqrt(2), |u1 - u0| = sqrt(2)|d|, so the prox
    of mu * w * |u1 - u0| soft-thresholds d at sqrt(2) * mu * w and keeps the average (on a
    2-sample pair that IS the exact 1-D TV prox). Kamilov's parallel-proximal approximation
    averages the K term proxes, each taken with mu = K * lam:

        prox_tv(v) ~= (1/K) sum_terms prox_{K lam f_term}(v)    (detail threshold sqrt(2) K lam w)

    which matches the exact prox to first order in lam. Samples left without a partner (the
    first one for shift 1, the last one when the length minus the shift is odd) pass through
    that term unchanged, so odd sizes lose nothing and nothing wraps around (Antipa's code
    rolls circularly). Terms with no pair (axis shorter than 2, or 3 for shift 1) or zero
    weight are left out of K, so a 2-sample signal is denoised exactly. Non-expansive (an
    average of proxes). ``shifts`` picks the pairings; (0, 1) covers every difference once.
    Limits: one call moves a sample by at most lam * (sum of its edge weights), exactly like the
    exact prox, but it closes each difference by only ~1/K of the way however large lam * w
    is, so with large beta_t one call stays far from the exact prox (which flattens time).
    """
    _check_video(v)
    lam = _check_weight("lam", lam)
    beta_t = _check_weight("beta_t", beta_t)
    if not shifts or any(s not in (0, 1) for s in shifts) or len(set(shifts)) != len(shifts):
        raise ConfigError(f"prox_tv_haar: shifts must be distinct values from (0, 1), got {shifts}")
    terms = [
        (dim, s, (v.shape[dim] - s) // 2, weight)
        for dim, weight in _axis_weights(beta_t)
        for s in shifts
        if weight > 0 and (v.shape[dim] - s) // 2 >= 1
    ]
    out = v.clone()
    if lam == 0 or not terms:
        return out
    n_terms = len(terms)
    for dim, shift, pairs, weight in terms:
        first = [slice(None)] * 4
        second = [slice(None)] * 4
        first[dim] = slice(shift, shift + 2 * pairs, 2)
        second[dim] = slice(shift + 1, shift + 2 * pairs, 2)
        first, second = tuple(first), tuple(second)
        pair_diff = v[second] - v[first]
        # Pair prox with mu = K lam w: each sample moves by clamp(diff, +-2 mu) / 2 towards
        # the other; averaged over K terms that is clamp(...) / (2K).
        threshold = 2.0 * n_terms * lam * weight
        move = pair_diff.clamp(-threshold, threshold) / (2.0 * n_terms)
        out[first] += move
        out[second] -= move
    return out


# --------------------------------------------------------------------------- with non-negativity


def prox_tv(
    v: Tensor, lam: float, beta_t: float, method: str = "exact", **options
) -> Tensor | tuple[Tensor, ProxInfo]:
    """argmin_u 1/2||u - v||^2 + lam TV3_beta(u), exactly or by the Haar approximation.

    ``options`` go to ``prox_tv_exact`` (iters, tol, check_every, return_info) or to
    ``prox_tv_haar`` (shifts).
    """
    if method == "exact":
        return prox_tv_exact(v, lam, beta_t, **options)
    if method == "haar":
        return prox_tv_haar(v, lam, beta_t, **options)
    raise ConfigError(f"unknown TV prox method {method!r}; use 'exact' or 'haar'")


def prox_tv_nonneg(
    v: Tensor, lam: float, beta_t: float, method: str = "haar", **options
) -> Tensor | tuple[Tensor, ProxInfo]:
    """``nonneg(prox_tv(v, lam, beta_t, method))``: TV prox, then clamp at zero.

    With method="exact" this is exactly argmin_{u >= 0} 1/2||u - v||^2 + lam TV3_beta(u), in
    any dimension: if u = prox_tv(v), then v - u is a subgradient of lam TV3 at u, and also
    at max(u, 0) because clamping never reverses the sign of a neighbour difference (at most
    it makes it zero, where |.| accepts any slope in [-1, 1]); the remainder u - max(u, 0) is
    <= 0 and non-zero only where max(u, 0) = 0, i.e. in the normal cone of the orthant. So
    v - max(u, 0) satisfies the optimality condition (Yu, NeurIPS 2013, decomposing proxes;
    it relies on TV being anisotropic, a sum of |u_i - u_j|).
    With method="haar" it is the clamp of the approximation, not the prox of anything in
    particular. Antipa et al. use 1/2 (max(v, 0) + haar(v)) instead; that average halves the
    TV step and is not implemented here.
    """
    result = prox_tv(v, lam, beta_t, method=method, **options)
    if isinstance(result, tuple):  # prox_tv_exact(..., return_info=True)
        return nonneg(result[0]), result[1]
    return nonneg(result)
