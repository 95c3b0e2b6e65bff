"""Input validation shared by every estimator (batch MKC, WLS and the seeds' baselines).

Every regressor in mkc_stream solves the multi-channel linear model of the MKC paper, eq. (1):
``y_k = X_k theta + v_k`` with ``X_k`` of shape (m, n) and ``y_k`` of shape (m,). Callers may
pass the multi-channel shapes ``X (N, m, n), Y (N, m)`` or the ordinary single-channel shapes
``X (N, n), y (N,)``; both are normalised here to the 3-D/2-D form the kernels use.
"""
from __future__ import annotations

import numpy as np


class MKCInputError(ValueError):
    """Raised for input an estimator cannot use (shape, NaN/inf, too few samples, rank)."""


def as_multichannel(X, Y, *, min_samples: int | None = None):
    """Return ``(X3, Y2, single)`` with X3 (N, m, n) float64, Y2 (N, m) float64.

    ``single`` is True when the caller used the single-channel shapes, so that results such
    as ``weights_`` can be returned in the same shape family.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    if X.ndim == 2 and Y.ndim == 1:
        single = True
        X3 = X[:, None, :]
        Y2 = Y[:, None]
    elif X.ndim == 3 and Y.ndim == 2:
        single = False
        X3, Y2 = X, Y
    elif X.ndim == 2 and Y.ndim == 2 and Y.shape[1] == 1:
        single = True
        X3 = X[:, None, :]
        Y2 = Y
    else:
        raise MKCInputError(
            f"expected X (N, m, n) with Y (N, m), or X (N, n) with y (N,); got X{X.shape} and Y{Y.shape}"
        )
    N, m, n = X3.shape
    if Y2.shape != (N, m):
        raise MKCInputError(f"Y has shape {Y.shape}, expected {(N, m) if not single else (N,)} to match X{X.shape}")
    if n == 0 or m == 0:
        raise MKCInputError("X has no columns or no channels")
    need = n if min_samples is None else min_samples
    if N * m < need:
        raise MKCInputError(f"too few samples: {N} samples x {m} channels < {need} equations needed for {n} unknowns")
    bad_x = ~np.isfinite(X3).all(axis=(1, 2))
    bad_y = ~np.isfinite(Y2).all(axis=1)
    bad = bad_x | bad_y
    if bad.any():
        idx = np.flatnonzero(bad)
        raise MKCInputError(
            f"{idx.size} sample(s) contain NaN or inf (first at index {idx[0]}); drop or repair them first"
        )
    return np.ascontiguousarray(X3), np.ascontiguousarray(Y2), single


def check_full_rank(X3: np.ndarray) -> None:
    """Raise MKCInputError when the stacked design matrix cannot identify theta."""
    N, m, n = X3.shape
    A = X3.reshape(N * m, n)
    scale = np.sqrt((A * A).sum(axis=0))
    if np.any(scale == 0):
        cols = np.flatnonzero(scale == 0).tolist()
        raise MKCInputError(f"X is rank deficient: column(s) {cols} are all zero")
    rank = np.linalg.matrix_rank(A / scale)
    if rank < n:
        raise MKCInputError(f"X is rank deficient (rank {rank} < {n} unknowns); theta is not identifiable")


def per_channel(value, m: int, name: str) -> np.ndarray:
    """Broadcast a scalar or a length-m sequence of positive numbers to shape (m,)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(m, float(arr))
    if arr.shape != (m,):
        raise MKCInputError(f"{name} must be a scalar or have one value per channel ({m}); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise MKCInputError(f"{name} must be finite and > 0; got {arr.tolist()}")
    return arr


class LinearModelMixin:
    """predict/score shared by every linear estimator; expects ``coef_`` (n,)."""

    def predict(self, X):
        X = np.asarray(X, dtype=np.float64)
        if not hasattr(self, "coef_"):
            raise RuntimeError(f"{type(self).__name__} is not fitted yet; call fit(X, Y) first")
        return X @ self.coef_

    def residuals(self, X, Y):
        X3, Y2, single = as_multichannel(X, Y, min_samples=1)
        R = Y2 - np.einsum("kmn,n->km", X3, self.coef_)
        return R[:, 0] if single else R

    def get_params(self, deep=True):  # scikit-learn convention, enough for clone()
        import inspect

        sig = inspect.signature(type(self).__init__)
        return {k: getattr(self, k) for k in sig.parameters if k != "self"}

    def set_params(self, **params):
        for k, v in params.items():
            setattr(self, k, v)
        return self
