"""Correntropy weights and the MKC loss, eqs. (9)/(13) and (14)-(15) of the MKC paper."""
import math

from .._numba import kernel
from .normaliser import omh_h


@kernel
def residuals(X, Y, theta, R):
    """R[k, i] = y_k(i) - x_{k,i} theta   (e_k of eq. (3))."""
    N, m, n = X.shape
    for k in range(N):
        for i in range(m):
            s = Y[k, i]
            for j in range(n):
                s -= X[k, i, j] * theta[j]
            R[k, i] = s


@kernel
def weight_exponent_scale(sigma, d):
    """1 / (2 d^2 sigma^2): w = exp(-e^2 * this). One formula for batch and stream (same rounding)."""
    return 1.0 / (2.0 * d * d * sigma * sigma)


@kernel
def gauss_weight(t):
    """exp(-t) for t = e^2 / (2 d^2 sigma^2) >= 0: the series of normaliser.omh_h below t = 1e-3.

    There h = 1 - omh is within an ulp of exp(-t) (omh's truncation error < 2e-21) and costs a few
    multiplies instead of a libm call; with a wide kernel (sigma near its bound) every weight of the
    window takes this branch. One function for batch and stream, so both keep the same rounding.
    """
    return omh_h(t)[1]


@kernel
def kernel_weights(R, sigma, d, W):
    """W[k, i] = G_sigma_i(e_k(i)/d_i) = exp(-e^2 / (2 d_i^2 sigma_i^2))  (the W_k of eq. (14)).

    sigma_i = inf gives weight 1 (the WLS limit of Theorem 1).
    """
    N, m = R.shape
    for i in range(m):
        c = weight_exponent_scale(sigma[i], d[i])
        for k in range(N):
            W[k, i] = gauss_weight(R[k, i] * R[k, i] * c)


@kernel
def mkc_loss(R, sigma, d):
    """J_CL = sum_i sigma_i^2 (1 - (1/N) sum_k G_sigma_i(e_k(i)/d_i)),  eq. (9)/(13).

    Written with -expm1 so that the sigma -> inf limit (Theorem 1: J_CL -> J_WLS, eq. (12)) is
    reached without cancellation; sigma = inf returns J_WLS exactly.
    """
    N, m = R.shape
    J = 0.0
    for i in range(m):
        acc = 0.0
        for k in range(N):
            e = R[k, i] / d[i]
            if math.isinf(sigma[i]):
                acc += 0.5 * e * e
            else:
                s2 = sigma[i] * sigma[i]
                acc += s2 * (-math.expm1(-e * e / (2.0 * s2)))
        J += acc / N
    return J
