"""TV proximal operators: exact 1-D and 3-D proxes against independent solvers, Haar approximation."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear, minimize

from rngcam.errors import ConfigError, RngcamError
from rngcam.physics.tv_prox import (
    div3,
    grad3,
    nonneg,
    prox_tv,
    prox_tv_exact,
    prox_tv_haar,
    prox_tv_nonneg,
    tv1d_exact,
    tv3,
)

TIGHT = {"iters": 2000, "tol": 1e-7}  # ~1e-7 is the float64 floor of the gap certificate


# ----------------------------------------------------------------------------- references


def difference_matrix(shape, beta_t):
    """Explicit forward differences of a (C, T, H, W) video and the TV weight of each row."""
    idx = np.arange(math.prod(shape)).reshape(shape)
    rows, weights = [], []
    for axis, weight in ((3, 1.0), (2, 1.0), (1, beta_t)):
        if shape[axis] < 2 or weight == 0:
            continue
        a = np.take(idx, range(shape[axis] - 1), axis=axis).ravel()
        b = np.take(idx, range(1, shape[axis]), axis=axis).ravel()
        d = np.zeros((a.size, idx.size))
        d[np.arange(a.size), a] = -1.0
        d[np.arange(a.size), b] = 1.0
        rows.append(d)
        weights.append(np.full(a.size, weight))
    if not rows:
        return np.zeros((0, idx.size)), np.zeros(0)
    return np.vstack(rows), np.concatenate(weights)


def reference_prox(v, lam, beta_t):
    """prox of lam*TV via its dual, a bounded least-squares problem solved by BVLS (active set).

    min_u 1/2||u - v||^2 + lam sum w|Du|  <=>  u = v - D^T p,  p = argmin ||D^T p - v||, |p| <= lam w.
    """
    v = np.asarray(v, dtype=np.float64)
    d, w = difference_matrix(v.shape, beta_t)
    if d.shape[0] == 0 or lam == 0:
        return v.copy()
    fit = lsq_linear(d.T, v.ravel(), bounds=(-lam * w, lam * w), method="bvls", tol=1e-15)
    return (v.ravel() - d.T @ fit.x).reshape(v.shape)


def reference_prox_nonneg(v, lam, beta_t):
    """prox of lam*TV + indicator(u >= 0): dual min 1/2||(v - D^T p)_+||^2 over the box."""
    shape = np.shape(v)
    v = np.asarray(v, dtype=np.float64).ravel()
    d, w = difference_matrix(shape, beta_t)

    def dual(p):
        q = np.maximum(v - d.T @ p, 0.0)
        return 0.5 * q @ q, -d @ q

    fit = minimize(dual, np.zeros(w.size), jac=True, method="L-BFGS-B",
                   bounds=list(zip(-lam * w, lam * w)),
                   options={"ftol": 1e-16, "gtol": 1e-13, "maxiter": 20000, "maxcor": 30})
    return np.maximum(v - d.T @ fit.x, 0.0).reshape(shape)


def objective(u, v, lam, beta_t):
    u, v = u.double(), v.double()
    return float(0.5 * (u - v).square().sum() + lam * tv3(u, beta_t))


# ----------------------------------------------------------------------------- 1-D exact


@pytest.mark.parametrize("seed", range(4))
def test_tv1d_matches_bounded_least_squares_reference(seed):
    rng = np.random.default_rng(seed)
    for _ in range(25):
        n = int(rng.integers(1, 14))
        x = rng.normal(size=n)
        if rng.random() < 0.4:  # ties and plateaus exercise the algorithm's boundary cases
            x = np.round(2 * x) / 2
        lam = float(rng.choice([1e-3, 0.05, 0.3, 1.0, 3.0, 20.0]))
        u = tv1d_exact(torch.tensor(x), lam).numpy()
        assert np.allclose(u, reference_prox(x.reshape(1, 1, 1, n), lam, 0.0).ravel(), atol=1e-10)


def test_tv1d_long_random_walks_match_reference():
    rng = np.random.default_rng(7)
    x = np.cumsum(rng.normal(size=(3, 150)), axis=1)  # long segments: heavy backtracking
    for lam in (0.5, 5.0, 40.0):
        u = tv1d_exact(torch.tensor(x), lam).numpy()
        for row in range(3):
            ref = reference_prox(x[row].reshape(1, 1, 1, -1), lam, 0.0).ravel()
            assert np.allclose(u[row], ref, atol=1e-9)


def test_tv1d_satisfies_optimality_conditions():
    """x - u = D^T z with |z| <= lam, and z = lam*sign(Du) wherever u jumps."""
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.normal(size=(40, 3, 17)))
    lam = torch.tensor(rng.uniform(0.01, 2.0, size=(40, 3)))  # one weight per signal
    u = tv1d_exact(x, lam)
    z = (u - x).cumsum(-1)  # (D^T z)_j = z_{j-1} - z_j  =>  z_j = sum_{i<=j} (u - x)_i
    assert torch.allclose(z[..., -1], torch.zeros(()).double(), atol=1e-12)  # mean preserved
    z = z[..., :-1]
    lam_ = lam[..., None]
    assert bool((z.abs() <= lam_ + 1e-10).all())
    jump = u.diff(dim=-1)
    moving = jump.abs() > 1e-9
    assert bool(moving.any())
    assert torch.allclose(z[moving], (lam_ * jump.sign()).expand_as(z)[moving], atol=1e-10)


def test_tv1d_extremes():
    x = torch.tensor([[3.0, -1.0, 4.0, 1.0, -5.0]], dtype=torch.float32)
    assert torch.equal(tv1d_exact(x, 0.0), x)
    flat = tv1d_exact(x, 1e12)
    assert flat.dtype == torch.float32
    assert torch.allclose(flat, x.mean().expand_as(x))
    assert torch.equal(tv1d_exact(x[:, :1], 5.0), x[:, :1])
    pair = tv1d_exact(torch.tensor([0.0, 1.0]), 0.2)
    assert torch.allclose(pair, torch.tensor([0.2, 0.8]))
    with pytest.raises(ConfigError):
        tv1d_exact(x, -1.0)


# ----------------------------------------------------------------------------- 3-D exact


@pytest.mark.parametrize("shape", [(2, 3, 3, 3), (1, 2, 3, 4), (1, 5, 1, 3)])
@pytest.mark.parametrize("lam,beta_t", [(0.1, 1.0), (0.3, 10.0), (0.2, 0.0), (0.05, 1e4)])
def test_prox_exact_matches_reference(shape, lam, beta_t):
    v = torch.tensor(np.random.default_rng(3).normal(size=shape))
    u, info = prox_tv_exact(v, lam, beta_t, return_info=True, **TIGHT)
    ref = reference_prox(v.numpy(), lam, beta_t)
    err = float(np.sqrt(((u.numpy() - ref) ** 2).sum()))
    assert err <= info.error_bound + 1e-9  # the gap certificate really bounds the error
    assert np.allclose(u.numpy(), ref, atol=1e-6)


def test_prox_exact_on_one_axis_is_tv1d():
    rng = np.random.default_rng(4)
    along_t = torch.tensor(rng.normal(size=(3, 9, 1, 1)))
    assert torch.allclose(prox_tv_exact(along_t, 0.2, 10.0),
                          tv1d_exact(along_t[:, :, 0, 0], 2.0)[:, :, None, None], atol=1e-12)
    along_x = torch.tensor(rng.normal(size=(2, 1, 1, 11)))
    assert torch.allclose(prox_tv_exact(along_x, 0.3, 5.0), tv1d_exact(along_x, 0.3), atol=1e-12)
    rows = torch.tensor(rng.normal(size=(2, 1, 4, 7)))  # H rows coupled only through D_y
    with_y = prox_tv_exact(rows, 0.3, 0.0, **TIGHT)
    assert not torch.allclose(with_y, tv1d_exact(rows, 0.3), atol=1e-3)


def test_prox_exact_beats_haar_and_perturbations():
    gen = torch.Generator().manual_seed(5)
    v = torch.rand(2, 5, 6, 7, generator=gen, dtype=torch.float64)
    lam, beta_t = 0.08, 3.0
    u = prox_tv_exact(v, lam, beta_t, iters=1000, tol=1e-5)  # objective excess <= (1e-5 |v|)^2/2
    best = objective(u, v, lam, beta_t)
    assert best < objective(prox_tv_haar(v, lam, beta_t), v, lam, beta_t)
    assert best < objective(v, v, lam, beta_t)
    for scale in (1e-2, 1e-4):
        for _ in range(20):
            nudged = u + scale * torch.randn(u.shape, generator=gen, dtype=u.dtype)
            assert best <= objective(nudged, v, lam, beta_t) + 1e-12


def test_prox_exact_huge_lam_gives_means_along_coupled_axes():
    v = torch.rand(3, 4, 5, 6, generator=torch.Generator().manual_seed(6))
    for beta_t in (10.0, 1e4, 1e6):
        u = prox_tv_exact(v, 1e12, beta_t)
        assert torch.isfinite(u).all()
        assert torch.allclose(u, v.mean(dim=(1, 2, 3), keepdim=True).expand_as(v), atol=1e-6)
    per_frame = prox_tv_exact(v, 1e12, 0.0)  # no temporal coupling: each frame's mean
    assert torch.allclose(per_frame, v.mean(dim=(2, 3), keepdim=True).expand_as(v), atol=1e-6)


# ----------------------------------------------------------------------------- Haar


def haar_shrink_reference(x, threshold, shift):
    """Orthonormal single-level Haar of a 1-D signal from `shift`, detail soft-threshold, inverse."""
    y = x.copy()
    for i in range(shift, len(x) - 1, 2):
        a, d = (x[i] + x[i + 1]) / np.sqrt(2), (x[i + 1] - x[i]) / np.sqrt(2)
        d = np.sign(d) * max(abs(d) - threshold, 0.0)
        y[i], y[i + 1] = (a - d) / np.sqrt(2), (a + d) / np.sqrt(2)
    return y


@pytest.mark.parametrize("lam", [0.0, 0.05, 0.4, 3.0, 1e12])
def test_haar_on_a_pair_is_the_exact_prox(lam):
    v = torch.tensor([[[[0.3, 1.7]]], [[[2.0, -1.0]]]], dtype=torch.float64)  # (2, 1, 1, 2)
    assert torch.allclose(prox_tv_haar(v, lam, 7.0), tv1d_exact(v, lam))
    along_t = v.reshape(2, 2, 1, 1)
    assert torch.allclose(prox_tv_haar(along_t, lam, 7.0),
                          tv1d_exact(v, 7.0 * lam).reshape(2, 2, 1, 1))
    # the Haar form: detail coefficient thresholded at sqrt(2)*lam gives the same pair prox
    x = v[0, 0, 0].numpy()
    assert np.allclose(haar_shrink_reference(x, np.sqrt(2) * lam, 0), tv1d_exact(v, lam)[0, 0, 0])


@pytest.mark.parametrize("n", [3, 4, 7, 8])
def test_haar_is_the_average_of_shifted_shrinkages(n):
    """1-D signal: K = 2 shifts, each shrinking details at sqrt(2)*K*lam, averaged."""
    x = np.random.default_rng(n).normal(size=n)
    lam = 0.15
    expected = 0.5 * (haar_shrink_reference(x, np.sqrt(2) * 2 * lam, 0)
                      + haar_shrink_reference(x, np.sqrt(2) * 2 * lam, 1))
    got = prox_tv_haar(torch.tensor(x).reshape(1, 1, 1, n), lam, 1.0)
    assert np.allclose(got.numpy().ravel(), expected, atol=1e-12)


def test_haar_odd_sizes_keep_every_sample():
    v = torch.zeros(1, 5, 7, 3, dtype=torch.float64)
    v[0, -1, -1, -1] = 1.0  # a spike on the last sample of every odd axis
    v[0, 0, 0, 0] = -1.0  # and on the first
    u = prox_tv_haar(v, 0.05, 2.0)
    assert u[0, -1, -1, -1] < 1.0 and u[0, 0, 0, 0] > -1.0  # both were smoothed, not dropped
    assert torch.allclose(u.sum(), v.sum(), atol=1e-12)  # no wrap, no loss: the sum is kept
    assert u[0, 0, 0, 1] < 0 and u[0, -1, -1, -2] > 0  # no wrap-around to the far side
    assert float(u[0, -1, -1, 0]) == 0.0


def test_haar_equals_exact_prox_while_no_difference_changes_sign():
    """For small lam both move each sample by lam * (weighted sum of neighbour signs): this
    pins the threshold scaling K * lam (a wrong K would move samples by a multiple of that)."""
    gen = torch.Generator().manual_seed(9)
    shape = (2, 5, 6, 7)
    v = (torch.randperm(math.prod(shape), generator=gen).double() / 100).reshape(shape)
    lam = 1e-5  # neighbour differences are >= 0.01, far above any move
    for beta_t in (0.0, 1.0, 10.0):
        weights = torch.tensor([beta_t, 1.0, 1.0], dtype=torch.float64).view(3, 1, 1, 1, 1)
        first_order = v + lam * div3(weights * grad3(v).sign())  # v - lam D^T (w sign(Dv))
        assert torch.allclose(prox_tv_haar(v, lam, beta_t), first_order, rtol=0, atol=1e-13)
        assert torch.allclose(prox_tv_exact(v, lam, beta_t, **TIGHT), first_order, atol=1e-9)


# ----------------------------------------------------------------------------- shared properties


small_videos = st.tuples(
    st.integers(1, 2), st.integers(1, 4), st.integers(1, 4), st.integers(1, 5), st.integers(0, 2**31)
)


@settings(max_examples=12, deadline=None)
@given(small_videos, st.sampled_from([0.01, 0.2, 1.0]), st.sampled_from([0.0, 1.0, 10.0]))
def test_proxes_are_non_expansive(spec, lam, beta_t):
    *shape, seed = spec
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(shape, generator=gen, dtype=torch.float64)
    b = a + 0.5 * torch.randn(shape, generator=gen, dtype=torch.float64)
    dist = float((a - b).norm())
    for prox in (prox_tv_haar, lambda x, lam, beta: prox_tv_exact(x, lam, beta, **TIGHT)):
        assert float((prox(a, lam, beta_t) - prox(b, lam, beta_t)).norm()) <= dist + 1e-6


@pytest.mark.parametrize("method", ["exact", "haar"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lam_zero_is_identity_and_dtype_kept(method, dtype):
    v = torch.randn(3, 4, 5, 6, generator=torch.Generator().manual_seed(2), dtype=dtype)
    out = prox_tv(v, 0.0, 10.0, method=method)
    assert out.dtype == dtype and torch.equal(out, v) and out.data_ptr() != v.data_ptr()


@pytest.mark.parametrize("method", ["exact", "haar"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 1, 1, 2), (2, 1, 1, 1), (1, 2, 1, 1), (3, 3, 5, 2)])
def test_extreme_settings_stay_finite(method, dtype, shape):
    v = torch.rand(shape, generator=torch.Generator().manual_seed(8), dtype=dtype) * 100
    for lam in (1e-6, 1.0, 1e12):
        for beta_t in (0.0, 10.0, 1e4, 1e6):
            u = prox_tv(v, lam, beta_t, method=method)
            assert u.shape == v.shape and u.dtype == dtype and bool(torch.isfinite(u).all())
            # every TV prox keeps each channel's mean
            assert torch.allclose(u.double().mean(dim=(1, 2, 3)), v.double().mean(dim=(1, 2, 3)))


# ----------------------------------------------------------------------------- non-negativity


def test_exact_prox_then_clamp_is_prox_of_tv_plus_nonneg_in_3d():
    v = torch.tensor(np.random.default_rng(10).normal(size=(2, 3, 3, 3)))
    for lam, beta_t in ((0.1, 1.0), (0.3, 10.0)):
        got = prox_tv_nonneg(v, lam, beta_t, method="exact", **TIGHT)
        ref = reference_prox_nonneg(v.numpy(), lam, beta_t)
        assert (ref == 0).mean() > 0.2  # the constraint is active
        assert np.allclose(got.numpy(), ref, atol=1e-6)


def test_nonneg_and_haar_clamp():
    v = torch.tensor([[[[-1.0, 2.0, -3.0]]]])
    assert torch.equal(nonneg(v), torch.tensor([[[[0.0, 2.0, 0.0]]]]))
    out = prox_tv_nonneg(v, 0.1, 1.0)
    assert torch.equal(out, prox_tv_haar(v, 0.1, 1.0).clamp(min=0))


# ----------------------------------------------------------------------------- TV value, grad, div


def test_tv3_value_and_weights():
    v = torch.zeros(2, 2, 2, 3, dtype=torch.float64)
    v[0, 1, 0, 0] = 1.0  # one sample: 1 x-neighbour, 1 y-neighbour, 1 t-neighbour
    v[1, 0, 1, 2] = -2.0  # corner in another channel
    assert float(tv3(v, 0.0)) == pytest.approx(2.0 + 4.0)
    assert float(tv3(v, 10.0)) == pytest.approx(2.0 + 4.0 + 10.0 * (1.0 + 2.0))


def test_grad3_div3_adjoint():
    gen = torch.Generator().manual_seed(11)
    for shape in ((2, 3, 4, 5), (1, 1, 3, 1)):
        u = torch.randn(shape, generator=gen, dtype=torch.float64)
        g = torch.randn((3, *shape), generator=gen, dtype=torch.float64)
        assert float((grad3(u) * g).sum()) == pytest.approx(-float((u * div3(g)).sum()), rel=1e-12)
        d = grad3(u)
        assert float(d.abs().sum()) == pytest.approx(float(tv3(u, 1.0)), rel=1e-12)


# ----------------------------------------------------------------------------- errors


def test_bad_inputs_raise_clear_errors():
    v = torch.rand(1, 2, 3, 4)
    with pytest.raises(ConfigError, match="lam"):
        prox_tv_haar(v, -0.1, 1.0)
    with pytest.raises(ConfigError, match="beta_t"):
        prox_tv_exact(v, 0.1, float("nan"))
    with pytest.raises(ConfigError, match="shape"):
        prox_tv_haar(v[0], 0.1, 1.0)
    with pytest.raises(ConfigError, match="shifts"):
        prox_tv_haar(v, 0.1, 1.0, shifts=(0, 2))
    with pytest.raises(ConfigError, match="method"):
        prox_tv_nonneg(v, 0.1, 1.0, method="chambolle")
    bad = v.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(RngcamError, match="NaN"):
        prox_tv_exact(bad, 0.1, 1.0)
