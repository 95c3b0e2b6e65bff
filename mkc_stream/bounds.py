"""Robustness bound of Theorem 3 (eq. (22)) and its bound-minimising bandwidth (Corollary 2)."""
from __future__ import annotations

import math

from scipy.optimize import brentq


def _check(eps, N, M):
    if not (N / 2 < M < N):
        raise ValueError(f"Assumption 1 needs N/2 < M < N (more than half of the noises bounded); got N={N}, M={M}")
    if not eps >= 0:
        raise ValueError("eps must be >= 0")


def sigma_threshold(eps, N, M):
    """Theorem 3 holds for sigma > eps / sqrt(2 log(M / (N - M)))."""
    _check(eps, N, M)
    return eps / math.sqrt(2.0 * math.log(M / (N - M)))


def robustness_bound(sigma, eps, N, M, d=1.0, zeta=1.0):
    """xi of eq. (22): |theta - theta_o| <= xi for the scalar MKC regression (Theorem 3).

    eps bounds the normalised noise |v_k|/d of M of the N samples; zeta bounds |X_k| from below.
    Returns inf when sigma is at or below the theorem's threshold (the bound does not apply).
    """
    _check(eps, N, M)
    q = (N - M) / M
    p = math.exp(-eps * eps / (2.0 * sigma * sigma))
    if not p > q:
        return math.inf
    return d / zeta * (math.sqrt(-2.0 * sigma * sigma * math.log(p - q)) + eps)


def optimal_sigma(eps, N, M):
    """Corollary 2: the sigma minimising xi solves phi(p) = p log p / ((p - q) log(p - q)) = 1,
    p = exp(-eps^2 / (2 sigma^2)), q = (N - M)/M (Proposition 1: xi falls, then rises)."""
    _check(eps, N, M)
    if eps == 0:
        return 0.0
    q = (N - M) / M

    def g(p):  # phi(p) - 1 written without the division: decreasing in p on (q, 1)
        return p * math.log(p) - (p - q) * math.log(p - q)

    lo = q * (1 + 1e-12) if q > 0 else 1e-300
    p = brentq(g, lo, 1.0 - 1e-15, xtol=1e-15, rtol=1e-15, maxiter=200)
    return eps / math.sqrt(-2.0 * math.log(p))
