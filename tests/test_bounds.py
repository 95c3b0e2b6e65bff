"""Theorem 3 (eq. (22)), Proposition 1 and Corollary 2, checked numerically."""
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from mkc_stream import optimal_sigma, robustness_bound
from mkc_stream.bounds import sigma_threshold


def test_threshold_and_infinite_below_it():
    th = sigma_threshold(1.0, 100, 80)
    assert th == pytest.approx(1.0 / np.sqrt(2 * np.log(4.0)))
    assert robustness_bound(0.99 * th, 1.0, 100, 80) == np.inf
    assert np.isfinite(robustness_bound(1.01 * th, 1.0, 100, 80))
    with pytest.raises(ValueError):
        robustness_bound(1.0, 1.0, 100, 40)          # Assumption 1: M > N/2


def test_corollary_2_minimises_the_bound():
    for eps, N, M in [(1.0, 100, 80), (0.3, 50, 30), (2.0, 1000, 900)]:
        s_star = optimal_sigma(eps, N, M)
        lo = sigma_threshold(eps, N, M)
        res = minimize_scalar(lambda s: robustness_bound(s, eps, N, M), bounds=(lo * 1.0001, 100 * lo), method="bounded",
                              options={"xatol": 1e-10})
        assert s_star == pytest.approx(res.x, rel=1e-4)
        # Proposition 1: xi falls then rises around s_star, and grows without bound (Proposition 2)
        xi = lambda s: robustness_bound(s, eps, N, M)  # noqa: E731
        assert xi(0.8 * s_star) > xi(s_star) < xi(1.25 * s_star)
        assert xi(1e4 * s_star) > 100 * xi(s_star)


def test_theorem_3_holds_on_adversarial_data():
    """Scalar regression with N - M arbitrarily large outliers: the MKC minimiser is within xi."""
    rng = np.random.default_rng(3)
    N, M, d, eps = 60, 42, 1.0, 0.5
    x = rng.uniform(1.0, 2.0, N)                       # |X_k| > zeta = 1 (Assumption 2)
    v = rng.uniform(-eps, eps, N) * d
    v[M:] = rng.choice([-1, 1], N - M) * rng.uniform(50, 1e4, N - M)   # outliers
    theta_o = 1.7
    y = x * theta_o + v
    for sigma in (sigma_threshold(eps, N, M) * 1.05, optimal_sigma(eps, N, M), 3.0, 10.0):
        grid = np.linspace(theta_o - 50, theta_o + 50, 400001)
        J = sigma**2 * (1 - np.mean(np.exp(-((y[None, :] - np.outer(grid, x)) / d) ** 2 / (2 * sigma**2)), axis=1))
        theta_hat = grid[np.argmin(J)]
        assert abs(theta_hat - theta_o) <= robustness_bound(sigma, eps, N, M, d=d, zeta=1.0)
