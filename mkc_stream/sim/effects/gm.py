"""Gauss-Markov recursion (a loop NumPy cannot vectorise)."""
import math

from ..._numba import kernel


@kernel
def gm_filter(phi, w):
    """x_k = phi_k x_{k-1} + sqrt(1 - phi_k^2) w_k, x_0 = w_0: unit variance at every step."""
    n, d = w.shape
    x = w.copy()
    for k in range(1, n):
        a = phi[k]
        c = math.sqrt(max(1.0 - a * a, 0.0))
        for j in range(d):
            x[k, j] = a * x[k - 1, j] + c * w[k, j]
    return x
