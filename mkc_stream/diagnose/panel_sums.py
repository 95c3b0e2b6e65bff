"""Per-group sums of the panel's per-sample values (:func:`.block_sums.block_stats`), in one pass.

A group's sum runs over its samples in sample order, from 0.0: the additions, and their order,
of the one-hot sparse products they replace, so the sums are the same to the last bit (the
kernels never use fastmath, so a product and its sum are not fused into one rounding).
"""
import numpy as np

from .._numba import kernel

#: 21 packed products of the six time regressors, then the six regressors times the residual
N_REG = 27


@kernel
def group_sums(groups, n_groups, X):
    """(Q, n_groups, P): for each grouping q (a column of ``groups`` (N, Q), -1 = no group),
    the sum of the rows of X (N, P) in each group."""
    N, Q = groups.shape
    out = np.zeros((Q, n_groups, X.shape[1]))
    for n in range(N):
        for q in range(Q):
            g = groups[n, q]
            if g < 0:
                continue
            for j in range(X.shape[1]):
                out[q, g, j] += X[n, j]
    return out


@kernel
def regression_sums(groups, n_groups, PP, P, fi, zi):
    """(Q, n_groups, C, 27): per grouping, group and channel c, sum PP[:, j] fi[:, c] (j < 21,
    the packed X^T X of the time regressors over the inliers) and sum P[:, j] zi[:, c] (X^T e),
    without forming the (N, 27 C) products."""
    N, Q = groups.shape
    C = fi.shape[1]
    out = np.zeros((Q, n_groups, C, N_REG))
    for n in range(N):
        for q in range(Q):
            g = groups[n, q]
            if g < 0:
                continue
            for c in range(C):
                f = fi[n, c]
                z = zi[n, c]
                for j in range(21):
                    out[q, g, c, j] += PP[n, j] * f
                for j in range(6):
                    out[q, g, c, 21 + j] += P[n, j] * z
    return out
