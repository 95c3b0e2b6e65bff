"""Least median of squares and least trimmed squares (Rousseeuw & Leroy, 1987).

Both objectives are combinatorial; like PROGRESS and FAST-LTS we search over random elemental
subsets (n rows solved exactly). scikit-learn and statsmodels have neither estimator, hence the
numpy code. Every step is vectorised or a small lstsq, so numba buys nothing here.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from .._validation import LinearModelMixin, MKCInputError
from ._common import MAD_TO_SIGMA, stack_problem

_EVAL_CHUNK = 4_000_000  # residual-matrix entries evaluated at once (32 MB)


def elemental_fits(A, b, n_subsets, rng, rcond=1e-10):
    """Exact fits through n_subsets random n-row subsets; singular subsets are dropped.

    Returns thetas (k, n) with k <= n_subsets (subsets with duplicate rows or a reciprocal
    condition number below rcond are discarded rather than redrawn).
    """
    M, n = A.shape
    idx = rng.integers(0, M, size=(n_subsets, n))
    srt = np.sort(idx, axis=1)
    idx = idx[(np.diff(srt, axis=1) != 0).all(axis=1)] if n > 1 else idx
    if idx.shape[0] == 0:
        return np.empty((0, n))
    S, t = A[idx], b[idx]                                    # (k, n, n), (k, n)
    sv = np.linalg.svd(S, compute_uv=False)
    ok = sv[:, -1] > rcond * sv[:, 0]
    if not ok.any():
        return np.empty((0, n))
    return np.linalg.solve(S[ok], t[ok][..., None])[..., 0]


def order_statistic_of_squares(A, b, thetas, h):
    """h-th smallest squared residual (1-based) of every candidate theta: (k,)."""
    M = A.shape[0]
    out = np.empty(thetas.shape[0])
    step = max(1, _EVAL_CHUNK // max(M, 1))
    for s in range(0, thetas.shape[0], step):
        R2 = (b[:, None] - A @ thetas[s:s + step].T) ** 2     # (M, chunk)
        out[s:s + step] = np.partition(R2, h - 1, axis=0)[h - 1]
    return out


def _coverage(h, M, n, name="h"):
    if h is None:
        return (M + n + 1) // 2
    if isinstance(h, (float, np.floating)) and 0 < h <= 1:
        h = int(np.ceil(h * M))
    h = int(h)
    if not n <= h <= M:
        raise MKCInputError(f"{name}={h} must lie between n={n} and the number of equations N*m={M}")
    return h


class LMSRegressor(LinearModelMixin):
    """Least median of squares, theta = argmin med_i r_i^2 (eq. (22) of the entropy-like paper).

    The "median" is Rousseeuw's h-th order statistic with h = floor(M/2) + floor((n+1)/2) over the
    M = N*m stacked rows (the quantile that gives the 50% breakdown point); minimised over
    n_subsets random elemental fits, as PROGRESS does (no exact LMS search).

    Parameters: n_subsets (3000), quantile (None -> Rousseeuw's h; or an int h, or a fraction
    in (0, 1]), cutoff (2.5, for inlier_mask_), random_state (0), channel_scale.
    Attributes: coef_ (n,), objective_ (h-th smallest squared residual), scale_ (Rousseeuw &
    Leroy's LMS scale 1.4826 (1 + 5/(M - n)) sqrt(objective_)), inlier_mask_ (|r| <= cutoff *
    scale_, (N, m) or (N,)), n_subsets_ (non-singular subsets tried).
    """

    def __init__(self, n_subsets=3000, quantile=None, cutoff=2.5, random_state=0, channel_scale=None):
        self.n_subsets = n_subsets
        self.quantile = quantile
        self.cutoff = cutoff
        self.random_state = random_state
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        P = stack_problem(X, Y, self.channel_scale)
        A, b = P.A, P.b
        M, n = A.shape
        h = M // 2 + (n + 1) // 2 if self.quantile is None else _coverage(self.quantile, M, n, "quantile")
        h = min(max(h, 1), M)
        rng = np.random.default_rng(self.random_state)
        thetas = elemental_fits(A, b, int(self.n_subsets), rng)
        if thetas.shape[0] == 0:
            raise MKCInputError("every random elemental subset was singular; X has too little variety for LMS")
        obj = order_statistic_of_squares(A, b, thetas, h)
        best = int(np.argmin(obj))
        self.coef_ = thetas[best].copy()
        self.objective_ = float(obj[best])
        denom = max(M - n, 1)
        self.scale_ = MAD_TO_SIGMA * (1.0 + 5.0 / denom) * np.sqrt(self.objective_)
        r = np.abs(b - A @ self.coef_)
        self.inlier_mask_ = P.unstack(r <= self.cutoff * self.scale_)
        self.n_subsets_ = int(thetas.shape[0])
        return self


def _c_steps(A, b, theta, h, max_steps):
    """FAST-LTS concentration steps: LS on the h smallest squared residuals until the subset repeats.

    Each step cannot increase the trimmed sum (Rousseeuw & Van Driessen 2006, Theorem 1), and the
    subset sequence is finite, so equality of consecutive subsets is the stopping rule.
    Returns (theta, objective, subset (sorted indices), steps, converged).
    """
    prev = None
    steps = 0
    while True:
        r2 = (b - A @ theta) ** 2
        H = np.sort(np.argpartition(r2, h - 1)[:h])
        if prev is not None and np.array_equal(H, prev):
            return theta, float(np.partition(r2, h - 1)[:h].sum()), H, steps, True
        if steps >= max_steps:
            return theta, float(np.partition(r2, h - 1)[:h].sum()), H, steps, False
        theta_new, *_ = np.linalg.lstsq(A[H], b[H], rcond=None)
        theta, prev, steps = theta_new, H, steps + 1


class LTSRegressor(LinearModelMixin):
    """Least trimmed squares, theta = argmin sum_{i<=h} (r^2)_{i:M} (eq. (24) of the entropy-like paper).

    FAST-LTS without the nested subsampling of very large data: n_starts random elemental fits,
    two C-steps each, then C-steps to convergence from the n_best lowest trimmed sums.

    Parameters: h (coverage; None -> (N*m + n + 1)//2, or an int, or a fraction in (0, 1]),
    n_starts (500), n_best (10), max_csteps (100), random_state (0), channel_scale.
    Attributes: coef_ (n,), objective_ (trimmed sum of squares), h_, support_ and inlier_mask_ (the
    final h-subset, (N, m) or (N,)), scale_ (raw LTS scale with the Gaussian consistency factor),
    n_iter_ (C-steps of the winning start after the two initial ones), converged_.
    """

    def __init__(self, h=None, n_starts=500, n_best=10, max_csteps=100, random_state=0, channel_scale=None):
        self.h = h
        self.n_starts = n_starts
        self.n_best = n_best
        self.max_csteps = max_csteps
        self.random_state = random_state
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        P = stack_problem(X, Y, self.channel_scale)
        A, b = P.A, P.b
        M, n = A.shape
        h = _coverage(self.h, M, n)
        rng = np.random.default_rng(self.random_state)
        starts = elemental_fits(A, b, int(self.n_starts), rng)
        if starts.shape[0] == 0:
            raise MKCInputError("every random elemental subset was singular; X has too little variety for LTS")
        # stage 1: two C-steps from every start, keep the n_best trimmed sums
        stage1 = [_c_steps(A, b, th, h, 2) for th in starts]
        order = np.argsort([s[1] for s in stage1], kind="stable")
        best = None
        seen = []
        for i in order[: max(1, int(self.n_best))]:
            if any(np.array_equal(stage1[i][2], H) for H in seen):
                continue  # same subset -> same C-step path
            seen.append(stage1[i][2])
            cand = _c_steps(A, b, stage1[i][0], h, int(self.max_csteps))
            if best is None or cand[1] < best[1]:
                best = cand
        theta, obj, H, steps, conv = best
        self.coef_ = np.asarray(theta, dtype=np.float64)
        self.objective_ = obj
        self.h_ = h
        mask = np.zeros(M, dtype=bool)
        mask[H] = True
        self.support_ = P.unstack(mask)
        self.inlier_mask_ = self.support_
        # consistency at the normal: E[r^2 | r^2 <= q] = sigma^2 chi2_3(q) / (h/M), q = chi2_1^-1(h/M)
        frac = h / M
        cons = chi2.cdf(chi2.ppf(frac, 1), 3) / frac if frac < 1 else 1.0
        self.scale_ = float(np.sqrt(obj / h / cons)) if cons > 0 else float("nan")
        self.n_iter_ = int(steps)
        self.converged_ = bool(conv)
        return self
