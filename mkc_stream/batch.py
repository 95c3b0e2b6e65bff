"""Reference batch solvers: MKC (fixed kernel), MKC-EM (Algorithm 3) and WLS (its sigma -> inf limit).

Thin scikit-learn-style shells: validate, allocate the work arrays once, call the kernels.
"""
from __future__ import annotations

import warnings

import numpy as np

from ._validation import LinearModelMixin, MKCInputError, as_multichannel, check_full_rank, per_channel
from .kernels import OK, NOT_CONVERGED, STATUS_TEXT
from .kernels.em import mkc_em
from .kernels.mstep import mstep_fixed_point
from .robust import mad_sd

#: Bounds of the E-step search: the range over which the normaliser is verified against the
#: 40-digit reference (sigma in [0.05, 1000]); d in [1e-9 a, a] with a the truncation bound.
#: a spans the largest residual, so one spike at 100x the field (a saturated or glitched read: the
#: quadratic features put it at ~1e4 residual units) makes a ~1e5 times the inliers' d; with a
#: 1e-6 floor d was clamped there and every weight went flat (1.4 uT error at 3% of 5000 uT
#: spikes, 0.02 uT with 1e-9). Large a/d costs the normaliser nothing: its floor term is exact.
DEFAULT_SIGMA_BOUNDS = (0.05, 1000.0)
DEFAULT_D_BOUNDS = (1e-9, 1.0)
#: The paper's EM start (Example 1 and 2): a wide kernel, i.e. start close to WLS.
DEFAULT_SIGMA_START = 20.0
#: EM's start bandwidth from a given (high-breakdown) theta0: weights halve at ~2.4 d.
START_SIGMA_ROBUST = 2.0     # = kernels.window.START_SIGMA_ROBUST (the stream's restart_at)
#: Truncation bound a = A_FACTOR * max|e| (the paper leaves a free). With a = max|e| exactly, the
#: uniform-tail explanation costs nothing at the sample maximum and Gaussian data get fitted with a
#: heavy tail (Example 2 case 1: +4% error vs WLS); a 1.5x margin removes that and keeps the
#: one-sided-outlier case 6 robust (2x and 3x do not). Measured on seeds disjoint from tools/reproduce_paper.py.
DEFAULT_A_FACTOR = 1.5


class MKCConvergenceWarning(UserWarning):
    """The fit stopped at an iteration cap or on a degenerate weighted system."""


class _Workspace:
    """Work arrays for one problem size; the kernels never allocate."""

    def __init__(self, N, m, n, em_iter):
        self.R = np.empty((N, m))
        self.W = np.empty((N, m))
        self.A = np.empty((n, n))
        self.b = np.empty(n)
        self.x = np.empty(n)
        self.L = np.zeros((n, n))
        self.D = np.empty(n)
        self.ebuf = np.empty(N)
        self.tprev = np.empty(n)
        self.a = np.zeros(m)
        self.Hes = np.zeros((m, 3))
        self.hist_theta = np.full((em_iter + 1, n), np.nan)
        self.hist_sigma = np.full((em_iter + 1, m), np.nan)
        self.hist_d = np.full((em_iter + 1, m), np.nan)


def robust_scale(R: np.ndarray) -> np.ndarray:
    """Per-channel 1.4826 * MAD of residuals (N, m), floored so it is never 0."""
    mad = mad_sd(R, axis=0)
    rms = np.sqrt(np.mean(R * R, axis=0))
    floor = 1e-12 * (1.0 + np.max(np.abs(R), axis=0))
    return np.maximum(np.where(mad > 0, mad, rms), floor)


def wls_solve(X3, Y2, d):
    """theta = (X^T P X)^-1 X^T P Y with P = diag(1/d_i^2), eq. (7). Returns (theta, status)."""
    N, m, n = X3.shape
    ws = _Workspace(N, m, n, 0)
    theta = np.zeros(n)
    sigma_inf = np.full(m, np.inf)
    _, status, _ = mstep_fixed_point(X3, Y2, sigma_inf, d, theta, 1, 0.0, ws.R, ws.W, ws.A, ws.b, ws.x, ws.L, ws.D)
    # One pass is exact for WLS (weights do not depend on theta): NOT_CONVERGED only means
    # "no second pass was made to confirm it".
    return theta, (OK if status == NOT_CONVERGED else status)


class WLSRegressor(LinearModelMixin):
    """Weighted least squares, eq. (7): the sigma -> infinity limit of MKC (Theorem 1).

    d: nominal standard deviation per channel (P = diag(1/d_i^2)); None means 1 for all.
    """

    def __init__(self, d=None):
        self.d = d

    def fit(self, X, Y):
        X3, Y2, single = as_multichannel(X, Y)
        check_full_rank(X3)
        N, m, n = X3.shape
        d = np.ones(m) if self.d is None else per_channel(self.d, m, "d")
        theta, status = wls_solve(X3, Y2, d)
        if status != OK:
            raise MKCInputError(f"WLS normal equations are {STATUS_TEXT[status]}")
        self.coef_ = theta
        self.d_ = d
        self.sigma_ = np.full(m, np.inf)
        W = np.ones((N, m))
        self.weights_ = W[:, 0] if single else W
        self.n_iter_ = 1
        self.converged_ = True
        return self


class MKCRegressor(LinearModelMixin):
    """Multi-kernel correntropy regression, with (em=True) or without the EM of (sigma, d).

    Parameters
    ----------
    em : bool
        True: MKC-EM (Algorithm 3), sigma and d are starting values and are re-estimated by
        maximum likelihood of the truncated MKC-induced pdf (Algorithm 2) between M-steps.
        False: MKC with fixed kernel parameters (Algorithm 1 only).
    sigma, d : float or array (m,), optional
        Kernel bandwidth and nominal standard deviation per channel. sigma defaults to 20 (the
        paper's EM start) when em=True and must be given when em=False. d defaults to a robust
        scale (1.4826 MAD) of the ordinary least-squares residuals of each channel.
    max_em_iter, em_tol : EM rounds cap and the relative theta change that stops EM early.
    max_iter, tol : fixed-point cap and threshold psi of Algorithm 1.
    sigma_bounds : (lo, hi) box of the E-step for sigma.
    d_bounds : (lo, hi) box for d as fractions of the truncation bound a.
    theta0 : array (n,), optional
        Start Algorithm 3 here instead of at the WLS solution (the paper's start). A correntropy
        fit, like any redescending M-estimator, cannot undo a start that gross high-leverage
        outliers have already dragged away; a high-breakdown start (MM-estimation's recipe) fixes
        that. d then defaults to the robust scale of the residuals at theta0, and sigma (em=True) to
        START_SIGMA_ROBUST: the first M-step must keep the start's robustness, where the paper's
        sigma = 20 (weights ~1 out to 20 d) suits its least-squares start.
    a : float, optional
        Truncation bound of the pdf's domain [-a, a] (same units as Y). None: a_factor times the
        largest absolute residual of the channel, re-evaluated at every E-step.
    estep_max_iter, estep_gtol : BFGS caps of the E-step.
    sigma_pull : weak prior on sigma in nats per e-fold (kernels/estep.py); 0, the paper's ML, by
        default. The streaming calibrator uses StreamConfig.sigma_pull; pass the same value to
        reproduce a stream's window exactly.

    Attributes
    ----------
    coef_ (n,), sigma_ (m,), d_ (m,), weights_ (N, m) or (N,), a_ (m,), n_iter_ (EM rounds, 0 for
    em=False), n_fixed_point_iter_, converged_, status_, condition_ (of the equilibrated
    weighted normal matrix), history_ (dict of per-round theta, sigma, d).
    """

    def __init__(self, em=True, sigma=None, d=None, *, max_em_iter=10, em_tol=1e-6, max_iter=200, tol=1e-9,
                 sigma_bounds=DEFAULT_SIGMA_BOUNDS, d_bounds=DEFAULT_D_BOUNDS, a=None, a_factor=DEFAULT_A_FACTOR,
                 estep_max_iter=100, estep_gtol=1e-9, sigma_pull=0.0, theta0=None):
        self.em = em
        self.theta0 = theta0
        self.sigma = sigma
        self.d = d
        self.max_em_iter = max_em_iter
        self.em_tol = em_tol
        self.max_iter = max_iter
        self.tol = tol
        self.sigma_bounds = sigma_bounds
        self.d_bounds = d_bounds
        self.a = a
        self.a_factor = a_factor
        self.estep_max_iter = estep_max_iter
        self.estep_gtol = estep_gtol
        self.sigma_pull = sigma_pull

    def _start(self, n):
        if self.theta0 is None:
            return None
        theta = np.array(self.theta0, dtype=np.float64).ravel()
        if theta.shape != (n,) or not np.isfinite(theta).all():
            raise MKCInputError(f"theta0 must be {n} finite numbers; got {np.asarray(self.theta0).shape}")
        return theta

    def _initial_params(self, X3, Y2):
        N, m, n = X3.shape
        if self.sigma is None:
            if not self.em:
                raise MKCInputError("MKCRegressor(em=False) needs a kernel bandwidth: pass sigma=...")
            sigma = np.full(m, DEFAULT_SIGMA_START if self.theta0 is None else START_SIGMA_ROBUST)
        else:
            sigma = per_channel(self.sigma, m, "sigma")
        if self.d is None:
            start = self._start(n)
            if start is None:
                start, _ = wls_solve(X3, Y2, np.ones(m))
            R = Y2 - np.einsum("kmn,n->km", X3, start)
            d = robust_scale(R)
        else:
            d = per_channel(self.d, m, "d")
        return sigma.copy(), d.copy()

    def _check_params(self):
        """Refuse settings the kernels cannot run with (checked at fit, as scikit-learn does): a
        negative max_em_iter sized the history arrays below the one row the kernel writes, and a
        NaN tolerance or an infinite bound ran silently to the iteration caps."""
        def integer(name, lo):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not v >= lo:
                raise MKCInputError(f"{name} must be an integer >= {lo}; got {v!r}")

        def number(name, ok, what):
            v = getattr(self, name)
            try:
                ok = ok(float(v)) and np.isfinite(float(v))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise MKCInputError(f"{name} must be a finite number {what}; got {v!r}")

        integer("max_em_iter", 0)
        integer("max_iter", 1)
        integer("estep_max_iter", 0)
        for name in ("em_tol", "tol", "estep_gtol", "sigma_pull"):
            number(name, lambda v: v >= 0, ">= 0")
        number("a_factor", lambda v: v > 0, "> 0")
        if self.a is not None:
            number("a", lambda v: v > 0, "> 0")
        try:
            lo, hi = (float(v) for v in self.sigma_bounds)
            dlo, dhi = (float(v) for v in self.d_bounds)
        except (TypeError, ValueError):
            raise MKCInputError(f"sigma_bounds and d_bounds must be (lo, hi) pairs; got {self.sigma_bounds}, "
                                f"{self.d_bounds}") from None
        if not (0 < lo < hi < np.inf) or not (0 < dlo < dhi < np.inf):
            raise MKCInputError(f"bounds must satisfy 0 < lo < hi < inf; got sigma {self.sigma_bounds}, "
                                f"d {self.d_bounds}")
        return lo, hi, dlo, dhi

    def fit(self, X, Y):
        lo, hi, dlo, dhi = self._check_params()
        X3, Y2, single = as_multichannel(X, Y)
        check_full_rank(X3)
        N, m, n = X3.shape
        fixed_a = -1.0 if self.a is None else float(self.a)
        sigma, d = self._initial_params(X3, Y2)
        theta = self._start(n)
        if theta is None:
            theta, status = wls_solve(X3, Y2, d)
            if status != OK:
                raise MKCInputError(f"initial WLS solve failed: {STATUS_TEXT[status]}")
        em_iter = int(self.max_em_iter) if self.em else 0
        ws = _Workspace(N, m, n, em_iter)
        if self.em:
            rounds, fp_its, status, cond = mkc_em(
                X3, Y2, sigma, d, theta, fixed_a, float(self.a_factor), float(lo), float(hi), float(dlo), float(dhi),
                em_iter, float(self.em_tol), int(self.max_iter), float(self.tol), int(self.estep_max_iter),
                float(self.estep_gtol), float(self.sigma_pull), ws.R, ws.W, ws.A, ws.b, ws.x, ws.L, ws.D, ws.ebuf, ws.tprev, ws.a, ws.Hes,
                ws.hist_theta, ws.hist_sigma, ws.hist_d)
        else:
            fp_its, status, cond = mstep_fixed_point(X3, Y2, sigma, d, theta, int(self.max_iter), float(self.tol),
                                                     ws.R, ws.W, ws.A, ws.b, ws.x, ws.L, ws.D)
            rounds = 0
            ws.hist_theta = theta[None, :].copy()
            ws.hist_sigma = sigma[None, :].copy()
            ws.hist_d = d[None, :].copy()
        self.coef_ = theta
        self.sigma_ = sigma
        self.d_ = d
        self.a_ = ws.a if self.em else np.full(m, np.nan)
        self.weights_ = ws.W[:, 0].copy() if single else ws.W.copy()
        self.n_iter_ = int(rounds)
        self.n_fixed_point_iter_ = int(fp_its)
        self.converged_ = status == OK
        self.status_ = STATUS_TEXT[int(status)]
        self.condition_ = float(cond)
        k = rounds + 1
        self.history_ = {"theta": ws.hist_theta[:k].copy(), "sigma": ws.hist_sigma[:k].copy(),
                         "d": ws.hist_d[:k].copy()}
        if status not in (OK, NOT_CONVERGED):
            warnings.warn(f"MKC fit stopped early: {self.status_}; coef_ is the last good iterate",
                          MKCConvergenceWarning, stacklevel=2)
        return self


def mkc_loss(residuals, sigma, d):
    """The MKC loss J_CL of eq. (9)/(13) for residuals (N, m) or (N,)."""
    from .kernels.correntropy import mkc_loss as _loss

    R = np.asarray(residuals, dtype=np.float64)
    if R.ndim == 1:
        R = R[:, None]
    m = R.shape[1]
    s = np.asarray(sigma, dtype=np.float64)
    s = np.full(m, float(s)) if s.ndim == 0 else s
    return float(_loss(np.ascontiguousarray(R), s, per_channel(d, m, "d")))
