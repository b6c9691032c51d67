"""The normal-equation NNLS the PSF-edge fit uses: SciPy's minimiser on tall designs, including
rank-deficient ones, an all-zero answer and a non-convergence it reports."""

import numpy as np
import pytest
from scipy.optimize import nnls

from rngcam.recon.methods.nnls import nnls_normal


@pytest.mark.parametrize("seed", range(4))
def test_the_minimiser_is_scipys_on_tall_designs_with_a_sparse_answer(seed):
    rng = np.random.default_rng(seed)
    a = rng.random((400, 60)) + 0.1 * rng.standard_normal((400, 60))
    truth = np.where(rng.random(60) < 0.3, rng.random(60), 0.0)
    y = a @ truth + 0.01 * rng.standard_normal(400)
    x = nnls_normal(a, y)
    expected, res = nnls(a, y)
    assert (x >= 0).all()
    assert np.linalg.norm(a @ x - y) == pytest.approx(res, rel=1e-9)
    np.testing.assert_allclose(x, expected, atol=1e-8 * expected.max())
    assert 0 < (x > 0).sum() < 60  # some bounds active, some not: the active set moved both ways


def test_duplicate_columns_and_a_target_no_positive_mix_can_reach():
    rng = np.random.default_rng(5)
    a = rng.random((50, 4))
    a = np.concatenate([a, a[:, :1]], 1)  # a repeated column: the active block may be singular
    y = a[:, 0] * 2 + a[:, 2]
    x = nnls_normal(a, y)
    assert np.linalg.norm(a @ x - y) < 1e-9 and (x >= 0).all()
    assert x[0] + x[4] == pytest.approx(2) and x[2] == pytest.approx(1)
    np.testing.assert_array_equal(nnls_normal(a, -y), np.zeros(5))  # every column points away


def test_it_says_when_it_does_not_converge():
    rng = np.random.default_rng(37)  # a problem whose active set must drop a column on the way
    a = rng.random((40, 6))
    y = rng.standard_normal(40) + a @ rng.random(6)
    with pytest.raises(RuntimeError, match="no convergence"):
        nnls_normal(a, y, maxiter=0)
    assert np.linalg.norm(a @ nnls_normal(a, y) - y) == pytest.approx(nnls(a, y)[1], rel=1e-9)
