"""Huber M-estimator with a jointly estimated scale (sklearn.linear_model.HuberRegressor)."""
from __future__ import annotations

import numpy as np

from .._validation import LinearModelMixin
from ._common import import_sklearn_linear_model, stack_problem


class HuberRegressor(LinearModelMixin):
    """Huber M-estimator, psi(t) = clip(t, -epsilon, epsilon) on residuals scaled by sigma.

    Why scikit-learn's HuberRegressor (alpha=0, fit_intercept=False) rather than IRLS with a MAD
    scale: it minimises Owen's (2007) concomitant objective
        sum_i [sigma + sigma * H_eps(r_i / sigma)],
    which is jointly convex in (theta, sigma) - one minimum, no start-dependence, no preliminary
    scale fit and no alternation whose fixed point depends on when the MAD is updated - and the
    estimate is scale-equivariant. IRLS with a MAD scale (statsmodels RLM) solves nearly the same
    estimating equation; the tests check that the two agree.

    Parameters: epsilon (>1, 1.35 gives 95% Gaussian efficiency), max_iter, tol, channel_scale.
    Attributes: coef_ (n,), scale_ (the concomitant sigma; its first-order condition is
    mean(min(z^2, eps^2)) = 1, so it is not the Gaussian sd: about 0.85 sd at eps = 1.35),
    weights_ (IRLS weights min(1, eps sigma/|r|), (N, m) or (N,)), inlier_mask_ (|r| <= eps
    sigma), n_iter_, converged_.
    """

    def __init__(self, epsilon=1.35, max_iter=1000, tol=1e-8, channel_scale=None):
        self.epsilon = epsilon
        self.max_iter = max_iter
        self.tol = tol
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        lm = import_sklearn_linear_model()
        P = stack_problem(X, Y, self.channel_scale)
        model = lm.HuberRegressor(epsilon=self.epsilon, alpha=0.0, fit_intercept=False,
                                  max_iter=self.max_iter, tol=self.tol)
        model.fit(P.A, P.b)
        self.coef_ = np.asarray(model.coef_, dtype=np.float64).reshape(-1)
        self.scale_ = float(model.scale_)
        r = np.abs(P.b - P.A @ self.coef_)
        cut = self.epsilon * self.scale_
        self.weights_ = P.unstack(np.where(r > cut, cut / np.maximum(r, 1e-300), 1.0))
        self.inlier_mask_ = P.unstack(r <= cut)
        self.n_iter_ = int(model.n_iter_)
        self.converged_ = self.n_iter_ < self.max_iter
        return self
