"""Least absolute deviations, solved exactly as a linear program (scipy's HiGHS)."""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.optimize import linprog

from .._validation import LinearModelMixin
from ._common import stack_problem


def lad_fit(A: np.ndarray, b: np.ndarray):
    """Exact minimiser of sum_i |b_i - A_i theta| -> (theta, objective, iterations, converged).

    Solved through the LP dual  max_d b^T d  s.t.  A^T d = 0, -1 <= d <= 1  (n equality rows and
    box bounds: hundreds of times faster in HiGHS than the primal with 2M slack variables).
    theta is the multiplier of A^T d = 0: from the Lagrangian, the dual's optimal value as a
    function of the right-hand side c is  -min_theta [sum|b - A theta| + c^T theta],  so its
    sensitivity (scipy's eqlin.marginals of the minimised -b^T d) is -theta.
    """
    M, n = A.shape
    res = linprog(-b, A_eq=A.T, b_eq=np.zeros(n), bounds=(-1.0, 1.0), method="highs")
    if res.status == 0 and res.eqlin is not None:
        theta = -np.asarray(res.eqlin.marginals, dtype=np.float64)
        obj = float(np.abs(b - A @ theta).sum())
        # strong duality: the primal value equals the dual's; a gap means degenerate marginals
        if abs(obj - (-res.fun)) <= 1e-7 * max(1.0, abs(res.fun)):
            return theta, obj, int(res.nit), True
    return lad_primal(A, b)


def lad_primal(A: np.ndarray, b: np.ndarray):
    """The primal LP  min 1^T(u+ + u-)  s.t.  A theta + u+ - u- = b,  u+, u- >= 0  (the fallback)."""
    M, n = A.shape
    c = np.concatenate([np.zeros(n), np.ones(2 * M)])
    I = sparse.identity(M, format="csc")
    A_eq = sparse.hstack([sparse.csc_matrix(A), I, -I], format="csc")
    lb = np.concatenate([np.full(n, -np.inf), np.zeros(2 * M)])
    res = linprog(c, A_eq=A_eq, b_eq=b, bounds=np.stack([lb, np.full(n + 2 * M, np.inf)], 1), method="highs")
    if res.x is None:
        raise RuntimeError(f"LAD linear program failed: {res.message}")
    theta = res.x[:n].copy()
    return theta, float(np.abs(b - A @ theta).sum()), int(res.nit), res.status == 0


class LADRegressor(LinearModelMixin):
    """Least absolute deviations (L1) regression, theta = argmin sum |y - X theta|, exactly (LP).

    Parameters
    ----------
    channel_scale : None, float or (m,) - per-channel scale d_i dividing rows and targets.

    Attributes
    ----------
    coef_ (n,), objective_ (the minimised sum of absolute scaled residuals), n_iter_ (HiGHS
    iterations), converged_.
    """

    def __init__(self, channel_scale=None):
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        P = stack_problem(X, Y, self.channel_scale)
        theta, obj, nit, ok = lad_fit(P.A, P.b)
        self.coef_ = theta
        self.objective_ = obj
        self.n_iter_ = nit
        self.converged_ = bool(ok)
        return self
