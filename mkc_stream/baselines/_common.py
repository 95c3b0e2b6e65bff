"""Shared plumbing of the comparison estimators: stacking, channel scaling, scale estimates.

Every baseline solves the multi-channel model y_k = X_k theta + v_k (MKC paper, eq. (1)) as one
ordinary regression on the N*m stacked rows. ``channel_scale`` d_i divides channel i's rows and
targets, i.e. the WLS weighting 1/d_i^2 of the paper's eq. (7), applied before the robust fit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_multichannel, check_full_rank, per_channel

#: Normal-consistency factor of the median absolute deviation, 1/Phi^-1(3/4).
MAD_TO_SIGMA = 1.482602218505602

SKLEARN_EXTRA = 'pip install "mkc-stream[baselines]"'


def import_sklearn_linear_model():
    """sklearn.linear_model, imported on first use: scikit-learn is the optional extra ``baselines``."""
    try:
        from sklearn import linear_model
    except ImportError as exc:
        raise ImportError(
            "this estimator wraps scikit-learn, which is not installed; it comes with the optional "
            f"extra 'baselines': {SKLEARN_EXTRA}"
        ) from exc
    return linear_model


@dataclass(frozen=True)
class Stacked:
    """The (N*m, n) problem a baseline actually solves, and how to map row results back."""

    A: np.ndarray        # (N*m, n) scaled design rows, sample-major (row k*m + i = channel i of sample k)
    b: np.ndarray        # (N*m,) scaled targets
    N: int
    m: int
    single: bool
    scale: np.ndarray    # (m,) channel_scale actually used

    def unstack(self, v) -> np.ndarray:
        """Row vector (N*m,) -> (N, m), or (N,) when the caller used single-channel shapes."""
        V = np.asarray(v).reshape(self.N, self.m)
        return V[:, 0].copy() if self.single else V.copy()


def stack_problem(X, Y, channel_scale=None, *, min_samples=None, full_rank=True) -> Stacked:
    """Validate (via as_multichannel / check_full_rank) and stack into one scaled regression."""
    X3, Y2, single = as_multichannel(X, Y, min_samples=min_samples)
    if full_rank:
        check_full_rank(X3)
    N, m, n = X3.shape
    d = np.ones(m) if channel_scale is None else per_channel(channel_scale, m, "channel_scale")
    A = (X3 / d[None, :, None]).reshape(N * m, n)
    b = (Y2 / d[None, :]).reshape(N * m)
    return Stacked(np.ascontiguousarray(A), np.ascontiguousarray(b), N, m, single, d)


def mad_scale(r: np.ndarray, floor_rel: float = 1e-12) -> float:
    """Robust residual scale 1.4826 * med|r|.

    Centred at zero rather than at med(r) (the entropy-like paper's eqs. (20)-(21)): these are
    regression residuals, whose location belongs to the fit. A small floor keeps thresholds
    positive when more than half the residuals are exactly zero (e.g. an interpolating fit).
    """
    r = np.abs(np.asarray(r, dtype=np.float64))
    s = MAD_TO_SIGMA * float(np.median(r))
    floor = floor_rel * max(float(np.max(r)) if r.size else 0.0, 1.0)
    return max(s, floor)


def check_positive(name: str, value, *, allow_zero=False) -> float:
    v = float(value)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite; got {value!r}")
    return v
