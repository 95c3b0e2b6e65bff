"""Least entropy-like (LEL) estimator of Indiveri, Entropy 11 (2009) 560-585.

With residuals r_i (i = 1..M, here the M = N*m stacked rows), eqs. (40)-(42):
    D = sum_j r_j^2,   q_i = r_i^2 / D,   H = -(1 / log M) sum_i q_i log q_i   (H = 0 if D = 0),
and eq. (46): theta_LEL = argmin_theta H. H is a normalised entropy of the relative squared
residuals: it is small when most residuals are small and a few are large, hence the robustness.
H is non-convex; the paper's multi-start rule (50)-(51) is implemented below.
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import minimize
from scipy.special import xlogy

from .._validation import LinearModelMixin, MKCInputError
from ._common import stack_problem

_NO_GRADIENT = {"nelder-mead", "powell", "cobyla", "cobyqa"}
#: a local solution predicting ||X theta|| > _RUNAWAY ||y|| has left the data behind (see fit)
_RUNAWAY = 10.0


def entropy_like(r) -> float:
    """H of eq. (42) for a residual vector (0 when every residual is 0)."""
    r = np.asarray(r, dtype=np.float64).ravel()
    M = r.size
    D = float(r @ r)
    if D == 0.0 or M < 2:
        return 0.0
    q = r * r / D
    return float(-xlogy(q, q).sum() / np.log(M))


def _h_and_grad(z, Q, b, logM):
    """H and dH/dz for theta = R^-1 z (A = QR), so residuals are r = b - Q z.

    Eq. (52) for a linear model (dr_i/dtheta = -a_i, dD/dtheta = -2 A^T r) simplifies, because
    sum_i dq_i = 0 cancels the "1 +" of (1 + log q_i), to
        dH/dtheta = (2 / (D log M)) A^T [ r o (log q + H log M) ],
    and dH/dz = R^-T dH/dtheta replaces A by Q. r_i log q_i -> 0 as r_i -> 0 (taken as 0).
    """
    r = b - Q @ z
    D = float(r @ r)
    if D == 0.0:
        return 0.0, np.zeros_like(z)
    q = r * r / D
    H = float(-xlogy(q, q).sum() / logM)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(r != 0.0, r * (np.log(q) + H * logM), 0.0)
    return H, (2.0 / (D * logM)) * (Q.T @ g)


def multistart_points(theta0) -> np.ndarray:
    """The paper's initial values, eqs. (50)-(51): theta_1 = theta0, theta_i orthogonal to every
    other theta_j and ||theta_i|| = ||theta0||, i = 1..n (rows of the returned (n, n) array).

    The paper completes theta0 by "a Gram-Schmidt algorithm" without saying from which vectors;
    we orthonormalise [theta0, e_1, ..., e_n] (Householder QR, a stable Gram-Schmidt), which is
    deterministic. Its Tables 1 and 3 show starts that are not this completion (they look
    random), so individual starts differ from the paper's; the rule itself is the same.
    If theta0 = 0 the other starts get unit norm instead of zero norm (all-zero starts would
    all coincide).
    """
    t0 = np.asarray(theta0, dtype=np.float64).ravel()
    n = t0.size
    nrm = float(np.linalg.norm(t0))
    if nrm == 0.0:
        return np.vstack([t0, np.eye(n)[: n - 1]]) if n > 1 else t0[None, :]
    Qb, _ = np.linalg.qr(np.column_stack([t0 / nrm, np.eye(n)]))
    U = Qb[:, :n].T * nrm
    U[0] = t0                        # Q's first column is +-theta0/||theta0||: keep theta0 exactly
    return U


class LeastEntropyLikeRegressor(LinearModelMixin):
    """Least entropy-like estimator (Indiveri 2009, eq. (46)) with the multi-start rule (50)-(51).

    Parameters
    ----------
    theta0 : None or (n,) - initial estimate theta_hat_0; None -> least squares (on the scaled
        rows), the paper's choice in all its examples.
    multistart : bool, True - run from the n starts of eqs. (50)-(51) and keep the lowest H (the
        paper's rule: "the best (local) solution ... is the one corresponding to the least value
        of H"); False runs from theta0 only.
    method : scipy.optimize.minimize method, "BFGS" with the analytic gradient (eq. (52)); the
        paper used Nelder-Mead ("Nelder-Mead" is accepted too).
    max_iter, tol : per local minimisation (tol is BFGS's gtol, or Nelder-Mead's fatol).
    channel_scale : None, scalar or (m,).

    Implementation choices (H and its minimisers are unchanged by them):
    * b is divided by the RMS residual of theta0 (H(c r) = H(r)), and the search runs in z = R theta
      with A = QR, so BFGS's identity initial Hessian suits any column scaling of X.
    * If theta0 already fits exactly (D = 0) H = 0 is the global minimum: theta0 is returned, as
      the paper advises (Sec. 4.1: a perfect LS fit makes any other estimator useless).
    * Not in the paper: a run that ends with ||X theta|| > 10 ||y|| is discarded (escaped_). H
      tends to H(X d) along any ray theta0 + t d, and on outlier-free Gaussian data that
      asymptote can be lower than the finite minima; the paper's local Nelder-Mead never went
      there, a quasi-Newton search can. If every run escapes, theta0 is returned with a warning.
    * On outlier-free Gaussian data LEL is markedly less accurate than LS (the paper's Table 2
      says as much): H is then nearly flat and its minima fit the noise.

    Attributes
    ----------
    coef_ (n,), objective_ (H at coef_), start_objective_ (H at theta0), starts_ (k, n),
    solutions_ (k, n), objectives_ (k,), escaped_ (k,) bool, n_iter_ (iterations of the winning
    start), converged_ (the winning local minimisation reported success).
    """

    def __init__(self, theta0=None, multistart=True, method="BFGS", max_iter=1000, tol=1e-8, channel_scale=None):
        self.theta0 = theta0
        self.multistart = multistart
        self.method = method
        self.max_iter = max_iter
        self.tol = tol
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        P = stack_problem(X, Y, self.channel_scale)
        A, b = P.A, P.b
        M, n = A.shape
        if M < 2:
            raise MKCInputError("the entropy-like objective needs at least 2 equations (log M > 0)")
        Q, R = np.linalg.qr(A)
        if self.theta0 is None:
            theta0 = solve_triangular(R, Q.T @ b)
        else:
            theta0 = np.asarray(self.theta0, dtype=np.float64).ravel()
            if theta0.shape != (n,) or not np.all(np.isfinite(theta0)):
                raise MKCInputError(f"theta0 must be {n} finite numbers; got {np.shape(self.theta0)}")
        r0 = b - A @ theta0
        D0 = float(r0 @ r0)
        self.start_objective_ = entropy_like(r0)
        if D0 <= (1e-12 * max(float(np.linalg.norm(b)), 1e-300)) ** 2:
            # exact fit up to rounding: D = 0 in (42), H = 0, nothing left to estimate
            self.start_objective_ = 0.0
            self.coef_ = theta0.copy()
            self.objective_ = 0.0
            self.starts_ = theta0[None, :].copy()
            self.solutions_ = theta0[None, :].copy()
            self.objectives_ = np.array([self.objective_])
            self.escaped_ = np.zeros(1, dtype=bool)
            self.n_iter_, self.converged_ = 0, True
            return self

        c = np.sqrt(D0 / M)                       # H is scale invariant: work on b / c, theta / c
        bs = b / c
        starts = multistart_points(theta0) if self.multistart else theta0[None, :]
        logM = np.log(M)
        method = str(self.method)
        use_grad = method.lower() not in _NO_GRADIENT
        opts = {"maxiter": int(self.max_iter)}
        if method.lower() == "bfgs":
            opts["gtol"] = float(self.tol)
        elif method.lower() == "nelder-mead":
            opts.update(fatol=float(self.tol), xatol=1e-10)
        sols, objs, results = [], [], []
        for th in starts:
            z0 = R @ (th / c)
            if use_grad:
                res = minimize(_h_and_grad, z0, args=(Q, bs, logM), jac=True, method=method, options=opts)
            else:
                res = minimize(lambda z: _h_and_grad(z, Q, bs, logM)[0], z0, method=method, options=opts)
            theta = solve_triangular(R, res.x) * c
            sols.append(theta)
            objs.append(entropy_like(b - A @ theta))
            results.append(res)
        # H(theta0 + t d) -> H(A d) as t -> inf: when no strong outlier pattern pulls H down near
        # the truth (e.g. outlier-free Gaussian noise), that limit can undercut every finite local
        # minimum and the search walks off with a vanishing gradient. Such a run found no
        # minimiser of (46), so it is not eligible ("escaped_").
        escaped = np.array([np.linalg.norm(A @ t) > _RUNAWAY * np.linalg.norm(b) for t in sols])
        self.starts_ = np.asarray(starts, dtype=np.float64)
        self.solutions_ = np.asarray(sols)
        self.objectives_ = np.asarray(objs)
        self.escaped_ = escaped
        if escaped.all():
            warnings.warn("every entropy-like minimisation escaped to infinity; returning theta0", RuntimeWarning,
                          stacklevel=2)
            self.coef_ = theta0.copy()
            self.objective_ = self.start_objective_
            self.n_iter_, self.converged_ = 0, False
            return self
        k = int(np.argmin(np.where(escaped, np.inf, objs)))
        self.coef_ = sols[k]
        self.objective_ = float(objs[k])
        self.n_iter_ = int(getattr(results[k], "nit", 0))
        self.converged_ = bool(results[k].success)
        return self
