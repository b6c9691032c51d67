"""Non-negative least squares on the normal equations, for tall designs with few active columns.

The PSF-edge fit (rngcam.recon.methods.psf_edge) solves min ||A x - y|| with x >= 0 for a design of
4,096 RS pixels by ~750 edge pixels, of which ~130 end non-zero. SciPy's `nnls` works on A itself;
the same active-set method (Lawson and Hanson) on G = A'A and c = A'y,
as Bro and De Jong's FNNLS does, solves only |P| x |P| systems of the active set P after one
product that forms G (faster there, the same solutions; bench/realistic.md, "the row-gain search where a
fit through a PSF too large ends unexplained").
"""

from __future__ import annotations

import numpy as np


def nnls_normal(a: np.ndarray, y: np.ndarray, maxiter: int | None = None) -> np.ndarray:
    """argmin ||a x - y||^2 over x >= 0 (a: (m, n), y: (m,)), by the active-set method on the normal
    equations. Raises RuntimeError where it does not converge within `maxiter` inner steps (3n)."""
    g, c = a.T @ a, a.T @ y
    n = len(c)
    maxiter = 3 * n if maxiter is None else maxiter
    tol = 10 * np.finfo(float).eps * max(float(np.abs(g).sum(0).max()), 1e-300) * n
    active = np.zeros(n, dtype=bool)
    x = np.zeros(n)
    w = c.copy()  # the negative gradient at x
    steps = 0
    while not active.all() and (w[~active]).max() > tol:
        active[np.flatnonzero(~active)[np.argmax(w[~active])]] = True
        s = _solve_active(g, c, active)
        while s[active].min() <= 0:  # a step back to the boundary: drop the columns it reaches
            steps += 1
            if steps > maxiter:
                raise RuntimeError(f"nnls_normal: no convergence within {maxiter} steps")
            back = active & (s <= 0)
            alpha = float(np.min(x[back] / (x[back] - s[back])))
            x = x + alpha * (s - x)
            active &= x > tol
            x[~active] = 0.0
            s = _solve_active(g, c, active)
        x = s
        w = c - g @ x
    return x


def _solve_active(g: np.ndarray, c: np.ndarray, active: np.ndarray) -> np.ndarray:
    """The unconstrained minimiser over the active columns (zero elsewhere); least squares where
    G's active block is singular."""
    s = np.zeros(len(c))
    idx = np.flatnonzero(active)
    block = g[np.ix_(idx, idx)]
    try:
        s[idx] = np.linalg.solve(block, c[idx])
    except np.linalg.LinAlgError:
        s[idx] = np.linalg.lstsq(block, c[idx], rcond=None)[0]
    return s
