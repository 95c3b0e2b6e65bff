"""Ridge and lasso: thin wrappers around scikit-learn (optional extra ``baselines``).

No intercept: the caller's X carries its own constant column when the model has one.
"""
from __future__ import annotations

import numpy as np

from .._validation import LinearModelMixin
from ._common import import_sklearn_linear_model, stack_problem


class RidgeRegressor(LinearModelMixin):
    """L2-penalised least squares, min ||y - X theta||^2 + alpha ||theta||^2 (sklearn.linear_model.Ridge).

    Parameters: alpha (>= 0), channel_scale (None, scalar or (m,)).
    Attributes: coef_ (n,).
    """

    def __init__(self, alpha=1.0, channel_scale=None):
        self.alpha = alpha
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        lm = import_sklearn_linear_model()
        P = stack_problem(X, Y, self.channel_scale)
        model = lm.Ridge(alpha=self.alpha, fit_intercept=False).fit(P.A, P.b)
        self.coef_ = np.asarray(model.coef_, dtype=np.float64).reshape(-1)
        return self


class LassoRegressor(LinearModelMixin):
    """L1-penalised least squares (sklearn.linear_model.Lasso, coordinate descent).

    sklearn's scaling of the objective: (1 / (2 N m)) ||y - X theta||^2 + alpha ||theta||_1 over
    the N*m stacked rows, so alpha does not grow with the sample count.

    Parameters: alpha (default 1e-3: mild shrinkage for O(1) coefficients), max_iter, tol,
    channel_scale.
    Attributes: coef_ (n,), n_iter_, converged_ (stopped on tol before max_iter), dual_gap_.
    """

    def __init__(self, alpha=1e-3, max_iter=10000, tol=1e-6, channel_scale=None):
        self.alpha = alpha
        self.max_iter = max_iter
        self.tol = tol
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        lm = import_sklearn_linear_model()
        P = stack_problem(X, Y, self.channel_scale)
        model = lm.Lasso(alpha=self.alpha, fit_intercept=False, max_iter=self.max_iter, tol=self.tol)
        model.fit(P.A, P.b)
        self.coef_ = np.asarray(model.coef_, dtype=np.float64).reshape(-1)
        self.n_iter_ = int(model.n_iter_)
        self.converged_ = self.n_iter_ < self.max_iter
        self.dual_gap_ = float(model.dual_gap_)
        return self
