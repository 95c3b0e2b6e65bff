"""RANSAC around an intercept-free least-squares fit (sklearn.linear_model.RANSACRegressor)."""
from __future__ import annotations

import numpy as np

from .._validation import LinearModelMixin, MKCInputError
from ._common import check_positive, import_sklearn_linear_model, mad_scale, stack_problem
from .lad import lad_fit


class RANSACRegressor(LinearModelMixin):
    """Random sample consensus (Fischler & Bolles) on the stacked rows.

    Parameters
    ----------
    residual_threshold : None or float
        Inlier band on the absolute (scaled) residual. None -> threshold_factor * 1.4826 * med|r|
        of an exact LAD fit: LAD's residual scale is barely moved by gross outliers, whereas
        scikit-learn's own default (MAD of y, not of residuals) has nothing to do with the noise.
    threshold_factor : float, 2.5 (Rousseeuw & Leroy's cut-off, eq. (26) of the entropy-like paper).
    min_samples : None or int - rows per random subset; None -> n (an elemental, exactly
        determined subset: no intercept is fitted).
    max_trials, stop_probability, random_state : passed to scikit-learn (fixed seed by default).
    channel_scale : None, scalar or (m,).

    Attributes
    ----------
    coef_ (n,), inlier_mask_ ((N, m), or (N,) single-channel), residual_threshold_, n_iter_
    (trials drawn), estimator_ (the fitted scikit-learn object).
    """

    def __init__(self, residual_threshold=None, threshold_factor=2.5, min_samples=None, max_trials=1000,
                 stop_probability=0.99, random_state=0, channel_scale=None):
        self.residual_threshold = residual_threshold
        self.threshold_factor = threshold_factor
        self.min_samples = min_samples
        self.max_trials = max_trials
        self.stop_probability = stop_probability
        self.random_state = random_state
        self.channel_scale = channel_scale

    def fit(self, X, Y):
        lm = import_sklearn_linear_model()
        P = stack_problem(X, Y, self.channel_scale)
        n = P.A.shape[1]
        if self.residual_threshold is None:
            theta0, *_ = lad_fit(P.A, P.b)
            thr = check_positive("threshold_factor", self.threshold_factor) * mad_scale(P.b - P.A @ theta0)
        else:
            thr = check_positive("residual_threshold", self.residual_threshold)
        min_samples = n if self.min_samples is None else self.min_samples
        model = lm.RANSACRegressor(
            estimator=lm.LinearRegression(fit_intercept=False),
            min_samples=min_samples,
            residual_threshold=thr,
            max_trials=self.max_trials,
            stop_probability=self.stop_probability,
            loss="absolute_error",
            random_state=self.random_state,
        )
        try:
            model.fit(P.A, P.b)
        except ValueError as exc:  # no consensus set: the threshold is too tight for this data
            raise MKCInputError(f"RANSAC found no valid consensus set ({exc}); raise residual_threshold") from exc
        self.estimator_ = model
        self.coef_ = np.asarray(model.estimator_.coef_, dtype=np.float64).reshape(-1)
        self.inlier_mask_ = P.unstack(np.asarray(model.inlier_mask_, dtype=bool))
        self.residual_threshold_ = float(thr)
        self.n_iter_ = int(model.n_trials_)
        return self
