"""M-step: the fixed-point solution of Algorithm 1, eqs. (15)-(16) of the MKC paper."""
import math

from .._numba import kernel
from . import OK, NOT_CONVERGED
from .correntropy import residuals, kernel_weights
from .linalg import spd_solve


@kernel
def accumulate_normal(X, Y, W, d, A, b):
    """A = sum_k X_k^T P W_k X_k,  b = sum_k X_k^T P W_k y_k  with P = diag(1/d_i^2)  (eq. (15)).

    Only the lower triangle is accumulated (n(n+1)/2 products per row), then mirrored.
    """
    N, m, n = X.shape
    for p in range(n):
        b[p] = 0.0
        for q in range(n):
            A[p, q] = 0.0
    for k in range(N):
        for i in range(m):
            c = W[k, i] * (1.0 / (d[i] * d[i]))
            if c == 0.0:
                continue
            y = Y[k, i]
            for p in range(n):
                xp = X[k, i, p] * c
                b[p] += xp * y
                for q in range(p + 1):
                    A[p, q] += xp * X[k, i, q]
    for p in range(n):
        for q in range(p + 1, n):
            A[p, q] = A[q, p]


@kernel
def mstep_fixed_point(X, Y, sigma, d, theta, max_iter, tol, R, W, A, b, x, L, D):
    """Algorithm 1: theta_{t+1} = [sum X^T P W(theta_t) X]^-1 [sum X^T P W(theta_t) y]  (eq. (16)).

    Iterates from the caller's theta (warm start) until ||theta_{t+1}-theta_t|| / ||theta_t|| <= tol
    (at least one iteration, as in Algorithm 1). On exit R and W hold the residuals and kernel
    weights at the returned theta. Returns (iterations, status, cond_estimate); on a singular
    system theta keeps its last good value.
    """
    n = X.shape[2]
    status = NOT_CONVERGED
    cond = math.inf
    it = 0
    while it < max_iter:
        it += 1
        residuals(X, Y, theta, R)
        kernel_weights(R, sigma, d, W)
        accumulate_normal(X, Y, W, d, A, b)
        st, cond = spd_solve(A, b, x, L, D, n)
        if st != OK:
            status = st
            break
        num = 0.0
        den = 0.0
        for j in range(n):
            num += (x[j] - theta[j]) ** 2
            den += theta[j] ** 2
            theta[j] = x[j]
        if math.sqrt(num) <= tol * max(math.sqrt(den), 1e-300):
            status = OK
            break
    residuals(X, Y, theta, R)
    kernel_weights(R, sigma, d, W)
    return it, status, cond
