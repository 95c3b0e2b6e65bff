"""Small dense SPD solves for the normal equations (n <= ~16), written out so C can mirror them.

The weighted normal matrix of the ellipsoid model mixes features of very different size, so we
solve with Jacobi equilibration: D A D y = D b, x = D y with D = diag(A_ii^-1/2). This makes the
Cholesky pivots O(1) and the condition number the one of the scaled problem (what float32 can
bear), without changing the solution in exact arithmetic.
"""
import math

from .._numba import kernel
from . import OK, SINGULAR, NONFINITE


@kernel
def spd_solve(A, b, x, L, D, n):
    """Solve A x = b for symmetric positive definite A[:n, :n]. Returns (status, cond_est).

    L (n x n) and D (n) are caller-provided scratch; A and b are not modified. The diagonal of
    L holds the inverse pivots 1/l_jj (multiplications instead of divisions in the per-sample
    path). cond_est is (max l_jj / min l_jj)^2 of the equilibrated factor, a cheap lower
    estimate of cond(DAD).
    """
    for i in range(n):
        aii = A[i, i]
        if not (aii > 0.0) or not math.isfinite(aii):
            return SINGULAR, math.inf
        D[i] = 1.0 / math.sqrt(aii)
    lmax = 0.0
    lmin = math.inf
    for j in range(n):
        s = 1.0                      # (D A D)_jj = 1 exactly
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 1e-14):          # not positive definite to working precision
            return SINGULAR, math.inf
        ljj = math.sqrt(s)
        inv = 1.0 / ljj
        L[j, j] = inv
        lmax = max(lmax, ljj)
        lmin = min(lmin, ljj)
        for i in range(j + 1, n):
            s = A[i, j] * D[i] * D[j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s * inv
    # forward: L z = D b ; backward: L^T y = z ; x = D y
    for i in range(n):
        s = b[i] * D[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s * L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s * L[i, i]
    for i in range(n):
        x[i] *= D[i]
        if not math.isfinite(x[i]):
            return NONFINITE, math.inf
    return OK, (lmax / lmin) ** 2
