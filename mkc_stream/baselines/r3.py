"""Robust regularized kernel regression (R3) of Zhu, Hoi & Lyu, IEEE TSMC-B 38(6) 2008, in the primal.

Objective, eq. (6) with the offset b of eq. (3):
    E(alpha, b) = sum_i V(u_i) + lam alpha^T K alpha,   u = K alpha + b 1 - y   (f - y, as in
    Algorithm 1 step 5),
V the Huber loss (4) or the Huber epsilon-insensitive loss (5). With a = |u| - eps:
    V = 0 (a <= 0),  a^2 (0 < a <= m),  m (2 a - m) (a > m);   eps = 0 gives (4).
(The paper's (5) prints u^2 on the quadratic pieces; continuity needs (u -+ eps)^2, as its
restatement in Sec. IV-D has.)

Newton step (Algorithm 1, eqs. (7)-(12)), re-derived. For a fixed partition of the points into
linear (S1/S5), quadratic (S2/S4) and dead (S3) zones, E is quadratic and its exact minimiser
solves (I0 = diag(1 on the quadratic zone), e_i = m sign(u_i) on linear points, -eps sign(u_i) on
quadratic points, 0 on dead ones; eq. (7)/(9)):
    (lam I + I0 K) alpha' + b' I0 1 = I0 y - e,        1^T alpha' = 0.                    (*)
The second row is dE/db = 0 after eliminating the first: dE/db = 2 1^T(I0(K alpha + b 1 - y) + e)
and the first row gives I0(...) + e = -lam alpha'. The paper's H, (10)-(12) and N put 1 where
I0 1 belongs (its b column) and its dE/db is a vector; (*) is the Newton step gamma = 1 of (10)
with the correct generalised Hessian. It has the paper's fixed point but not its iterates.
Sec. IV-D's e has the wrong sign on the quadratic zone: d/df (u - eps)^2 = 2 (f - y - eps), so
the quadratic points are pulled to the edge of the dead zone, y + eps sign(u), i.e. e = -eps sign(u)
(with the paper's +eps, the "Newton" direction is not a descent direction).
Block form (the paper's Sec. IV-C with the same correction; Q = quadratic zone, O = the rest):
    alpha'_O = -e_O / lam,   C = lam I + K_QQ,   r_Q = y_Q - e_Q - K_QO alpha'_O,
    b' = (1^T C^-1 r_Q + 1^T alpha'_O) / (1^T C^-1 1)      (corrected (13)),
    alpha'_Q = C^-1 (r_Q - b' 1)                           (corrected (14)).
Linear kernel (K = A A^T, f = A w + b, w = A^T alpha): multiplying (*) by A^T gives the same
step in the n-dimensional primal, O(M n^2) instead of O(|Q|^3):
    (lam I + A_Q^T A_Q) w' + b' A_Q^T 1 = A_Q^T y_Q - A^T e,   1^T A_Q w' + |Q| b' = 1^T y_Q - 1^T e,
and alpha = -V'(u) / (2 lam) recovers the dual coefficients.

Step size: gamma = 1 as the paper says; if E would rise (possible when the partition changes),
gamma is halved until it does not (backtracking: E is convex and the step a descent direction),
so E never increases. Stopping (Algorithm 1 step 8, garbled in print): stop when
a full step leaves the partition unchanged - then the gradient is exactly zero and, E being
convex, the point is the global minimiser - or when the relative decrease of E is <= tol.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .._validation import LinearModelMixin
from ._common import check_positive, mad_scale, stack_problem

#: Huber's 95%-efficiency tuning constant, and the default dead zone, in units of the residual scale.
M_FACTOR = 1.345
EPS_FACTOR = 0.5


def huber_eps_loss(u, m, eps=0.0):
    """V(u) of eqs. (4)/(5): 0 in |u| <= eps, (|u|-eps)^2 up to |u| = eps + m, then linear."""
    a = np.abs(u) - eps
    return np.where(a <= 0.0, 0.0, np.where(a <= m, a * a, m * (2.0 * a - m)))


def huber_eps_dloss(u, m, eps=0.0):
    """V'(u)."""
    a = np.abs(u) - eps
    return np.sign(u) * np.where(a <= 0.0, 0.0, 2.0 * np.minimum(a, m))


def _zones(u, m, eps):
    """Quadratic-zone mask, e of (*), and a zone label per point (sign * {0 dead, 1 quad, 2 linear})."""
    a = np.abs(u) - eps
    s = np.sign(u)
    quad = (a <= m) & (a > 0.0) if eps > 0 else (a <= m)
    lin = a > m
    e = np.where(lin, m * s, np.where(quad, -eps * s, 0.0))
    label = (s * np.where(lin, 2, np.where(quad, 1, 0))).astype(np.int8)
    return quad, e, label


def _kernel_step(K, y, quad, e, lam, fit_intercept, b):
    """Exact minimiser (*) of the quadratic model for a fixed partition (kernel form)."""
    Mn = y.size
    alpha = np.empty(Mn)
    O = ~quad
    alpha[O] = -e[O] / lam
    if not quad.any():
        return alpha, b                       # b is not pinned by any quadratic point: keep it
    KQ = K[np.ix_(quad, quad)]
    C = cho_factor(KQ + lam * np.eye(KQ.shape[0]), lower=True, check_finite=False)
    rQ = y[quad] - e[quad] - K[np.ix_(quad, O)] @ alpha[O]
    x = cho_solve(C, rQ, check_finite=False)
    if fit_intercept:
        one = cho_solve(C, np.ones(KQ.shape[0]), check_finite=False)
        b = (x.sum() + alpha[O].sum()) / one.sum()
        alpha[quad] = x - b * one
    else:
        alpha[quad] = x
    return alpha, b


def _linear_step(A, y, quad, e, lam, fit_intercept, b):
    """The same step in the primal w = A^T alpha of the linear kernel."""
    n = A.shape[1]
    AQ, yQ = A[quad], y[quad]
    G = AQ.T @ AQ + lam * np.eye(n)
    rhs = AQ.T @ yQ - A.T @ e
    if fit_intercept and quad.any():
        sQ = AQ.sum(axis=0)
        G = np.block([[G, sQ[:, None]], [sQ[None, :], np.array([[float(quad.sum())]])]])
        rhs = np.append(rhs, yQ.sum() - e.sum())
        sol = np.linalg.lstsq(G, rhs, rcond=None)[0] if lam == 0 else np.linalg.solve(G, rhs)
        return sol[:n], float(sol[n])
    sol = np.linalg.lstsq(G, rhs, rcond=None)[0] if lam == 0 else np.linalg.solve(G, rhs)
    return sol, b


def r3_fit(y, m, eps, lam, *, K=None, A=None, fit_intercept=True, coef0=None, b0=0.0, max_iter=100, tol=1e-12):
    """Algorithm 1 (R3) on a kernel matrix K (coefficients alpha) or a linear design A (coefficients w).

    Returns dict(coef, b, objective, n_iter, converged). coef0=None starts from regularised least
    squares (every point in the quadratic zone, e = 0), the standard initialisation.
    """
    linear = A is not None
    if linear:
        f_of = lambda c, bb: A @ c + bb
        reg = lambda c: lam * float(c @ c)
        step = lambda quad, e, bb: _linear_step(A, y, quad, e, lam, fit_intercept, bb)
    else:
        f_of = lambda c, bb: K @ c + bb
        reg = lambda c: lam * float(c @ (K @ c))
        step = lambda quad, e, bb: _kernel_step(K, y, quad, e, lam, fit_intercept, bb)

    def energy(c, bb):
        return float(huber_eps_loss(f_of(c, bb) - y, m, eps).sum()) + reg(c)

    if coef0 is None:  # regularised LS: every point quadratic, e = 0
        coef, b = step(np.ones(y.size, dtype=bool), np.zeros(y.size), b0)
    else:
        coef, b = np.asarray(coef0, dtype=np.float64).copy(), float(b0)
    E = energy(coef, b)
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        quad, e, label = _zones(f_of(coef, b) - y, m, eps)
        new, nb = step(quad, e, b)
        gamma, E_new = 1.0, energy(new, nb)
        d, db = new - coef, nb - b
        while E_new > E * (1 + 1e-15) + 1e-300 and gamma > 1e-10:
            gamma *= 0.5
            new, nb = coef + gamma * d, b + gamma * db
            E_new = energy(new, nb)
        if E_new > E:  # no decrease possible along the Newton direction: at the minimum up to rounding
            converged = True
            break
        dE = E - E_new
        coef, b, E = new, nb, E_new
        if gamma == 1.0 and np.array_equal(_zones(f_of(coef, b) - y, m, eps)[2], label):
            converged = True  # exact minimiser of the model whose partition it reproduces: grad E = 0
            break
        if dE <= tol * max(E, 1e-300):
            converged = True
            break
    return {"coef": coef, "b": float(b), "objective": E, "n_iter": it, "converged": converged}


def rbf_kernel(X1, X2, gamma):
    d2 = (X1 * X1).sum(1)[:, None] + (X2 * X2).sum(1)[None, :] - 2.0 * X1 @ X2.T
    return np.exp(-gamma * np.maximum(d2, 0.0))


class RobustKernelRegressor(LinearModelMixin):
    """Robust regularized kernel regression (R3), primal Newton algorithm (Algorithm 1).

    Parameters
    ----------
    loss : "huber" (eq. (4)) or "huber-eps" (eq. (5), the paper's "enhanced robust regression").
    kernel : "linear" (K = X X^T; also sets coef_ = X^T alpha, the linear API) or "rbf"
        (k(x, x') = exp(-gamma ||x - x'||^2); predict() uses the stored training rows).
    lam : float, 1e-3 - regularisation lambda of eq. (6) (absolute, as in the paper; for the
        linear kernel lam = 0 is allowed and gives the plain Huber M-estimator with a fixed m).
    m : None or float - switch from quadratic to linear loss (absolute residual units). None: m =
        1.345 sigma_hat, sigma_hat = 1.4826 med|u|, starting from the regularised-LS residuals and
        re-estimated after each complete run of Algorithm 1 with the Huber loss until it changes
        by < 0.1% (at most max_scale_iter runs); "huber-eps" then runs once more with that scale.
        The paper takes m as given; within each run it stays fixed.
    epsilon : None or float - dead-zone half-width of "huber-eps" (None: 0.5 sigma_hat); must be
        0/None for "huber". The paper states m > eps
        is needed; with loss (5) as written (switch at |u| = eps + m) any m > 0 works, so this
        is not enforced.
    gamma : None or float - RBF width; None -> 1 / (n * Var(X rows)) (scikit-learn's "scale").
    fit_intercept : bool, True - the offset b of eq. (3), unpenalised. Set it False when X carries
        its own constant column (the BASELINES variants do).
    max_iter (100, Newton steps per run), tol (1e-12 relative decrease of E), max_scale_iter (50),
    channel_scale (linear kernel only: it
        rescales rows, which an RBF kernel would not undo at predict time).

    Attributes
    ----------
    dual_coef_ (N*m,) alpha; intercept_ b; coef_ (n,) (linear kernel); X_fit_ (rbf); gamma_
    (rbf); m_, epsilon_; objective_ E; weights_ (min(1, (eps + m)/|u|): 1 in the quadratic and
    dead zones, decaying in the linear zone; (N, m) or (N,)); inlier_mask_ (|u| <= eps + m);
    n_iter_, converged_.
    """

    def __init__(self, loss="huber", kernel="linear", lam=1e-3, m=None, epsilon=None, gamma=None,
                 fit_intercept=True, max_iter=100, tol=1e-12, max_scale_iter=50, channel_scale=None):
        self.loss = loss
        self.kernel = kernel
        self.lam = lam
        self.m = m
        self.epsilon = epsilon
        self.gamma = gamma
        self.fit_intercept = fit_intercept
        self.max_iter = max_iter
        self.tol = tol
        self.max_scale_iter = max_scale_iter
        self.channel_scale = channel_scale

    def _check_params(self):
        if self.loss not in ("huber", "huber-eps"):
            raise ValueError(f"loss must be 'huber' or 'huber-eps'; got {self.loss!r}")
        if self.kernel not in ("linear", "rbf"):
            raise ValueError(f"kernel must be 'linear' or 'rbf'; got {self.kernel!r}")
        lam = check_positive("lam", self.lam, allow_zero=self.kernel == "linear")
        if self.loss == "huber" and self.epsilon not in (None, 0, 0.0):
            raise ValueError("epsilon is only used by loss='huber-eps'")
        if self.kernel == "rbf" and self.channel_scale is not None:
            raise ValueError("channel_scale is only supported with kernel='linear'")
        return lam

    def fit(self, X, Y):
        lam = self._check_params()
        linear = self.kernel == "linear"
        # coef_ of the linear kernel is the linear API's theta: require full rank; RBF needs no rank
        P = stack_problem(X, Y, self.channel_scale, full_rank=linear, min_samples=None if linear else 2)
        A, y = P.A, P.b
        if linear:
            kw = {"A": A}
        else:
            if self.gamma is None:
                v = float(A.var())
                gamma = 1.0 / (A.shape[1] * v) if v > 0 else 1.0
            else:
                gamma = check_positive("gamma", self.gamma)
            self.gamma_ = gamma
            self.X_fit_ = A.copy()
            kw = {"K": rbf_kernel(A, A, gamma)}
        huber_eps = self.loss == "huber-eps"
        common = dict(fit_intercept=self.fit_intercept, max_iter=int(self.max_iter), tol=float(self.tol), **kw)

        def resid(res):
            c = res["coef"]
            return (A @ c if linear else kw["K"] @ c) + res["b"] - y

        auto = self.m is None or (huber_eps and self.epsilon is None)
        n_iter = 0
        if auto:
            # m (and eps) in units of the residual scale. The scale is the fixed point of "Huber R3
            # fit, MAD rescale" from the regularised-LS residuals (the fixed point of an IRLS Huber
            # with MAD scale, like statsmodels' RLM); within each run m stays fixed. The scale is
            # found with eps = 0 even for "huber-eps": alternating with the dead zone inflates it
            # (a wide dead zone admits the outliers, which widens the MAD, which widens the zone).
            res = r3_fit(y, 1.0, 0.0, lam, **{**common, "max_iter": 0})
            sig = mad_scale(resid(res))
            for _ in range(max(1, int(self.max_scale_iter))):
                m_, eps_ = self._m_eps(sig, False)
                res = r3_fit(y, m_, 0.0, lam, coef0=res["coef"], b0=res["b"], **common)
                n_iter += res["n_iter"]
                sig_new = mad_scale(resid(res))
                done = abs(sig_new - sig) <= 1e-3 * sig
                sig = sig_new
                if done:
                    break
            if huber_eps:
                m_, eps_ = self._m_eps(sig, True)
                res = r3_fit(y, m_, eps_, lam, coef0=res["coef"], b0=res["b"], **common)
                n_iter += res["n_iter"]
        else:
            m_, eps_ = self._m_eps(None, huber_eps)
            res = r3_fit(y, m_, eps_, lam, **common)
            n_iter = res["n_iter"]
        u = resid(res)
        self.m_, self.epsilon_ = float(m_), float(eps_)
        self.intercept_ = res["b"] if self.fit_intercept else 0.0
        self.objective_ = res["objective"]
        self.n_iter_ = int(n_iter)
        self.converged_ = bool(res["converged"])
        if linear:
            self.coef_ = np.asarray(res["coef"], dtype=np.float64)
            self.dual_coef_ = -huber_eps_dloss(u, m_, eps_) / (2.0 * lam) if lam > 0 else None
        else:
            self.dual_coef_ = np.asarray(res["coef"], dtype=np.float64)
        band = eps_ + m_
        au = np.abs(u)
        self.weights_ = P.unstack(np.where(au > band, band / np.maximum(au, 1e-300), 1.0))
        self.inlier_mask_ = P.unstack(au <= band)
        return self

    def _m_eps(self, sig, huber_eps):
        m_ = M_FACTOR * sig if self.m is None else check_positive("m", self.m)
        if not huber_eps:
            return m_, 0.0
        eps_ = EPS_FACTOR * sig if self.epsilon is None else check_positive("epsilon", self.epsilon, allow_zero=True)
        return m_, eps_

    def predict(self, X):
        if not hasattr(self, "dual_coef_"):
            raise RuntimeError(f"{type(self).__name__} is not fitted yet; call fit(X, Y) first")
        X = np.asarray(X, dtype=np.float64)
        if self.kernel == "linear":
            return X @ self.coef_ + self.intercept_
        lead = X.shape[:-1]
        Kx = rbf_kernel(X.reshape(-1, X.shape[-1]), self.X_fit_, self.gamma_)
        return (Kx @ self.dual_coef_ + self.intercept_).reshape(lead)

    def residuals(self, X, Y):
        Y = np.asarray(Y, dtype=np.float64)
        return Y - self.predict(X)


class R3HuberRegressor(RobustKernelRegressor):
    """BASELINES "r3-huber": linear-kernel R3 with the Huber loss, no offset (X carries its own)."""

    def __init__(self, lam=1e-3, m=None, fit_intercept=False, max_iter=100, tol=1e-12, max_scale_iter=50,
                 channel_scale=None):
        super().__init__(loss="huber", kernel="linear", lam=lam, m=m, fit_intercept=fit_intercept,
                         max_iter=max_iter, tol=tol, max_scale_iter=max_scale_iter, channel_scale=channel_scale)


class R3HuberEpsRegressor(RobustKernelRegressor):
    """BASELINES "r3-huber-eps": linear-kernel R3 with the Huber epsilon-insensitive loss, no offset."""

    def __init__(self, lam=1e-3, m=None, epsilon=None, fit_intercept=False, max_iter=100, tol=1e-12,
                 max_scale_iter=50, channel_scale=None):
        super().__init__(loss="huber-eps", kernel="linear", lam=lam, m=m, epsilon=epsilon,
                         fit_intercept=fit_intercept, max_iter=max_iter, tol=tol, max_scale_iter=max_scale_iter,
                         channel_scale=channel_scale)
