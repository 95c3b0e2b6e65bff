"""Each jitted kernel against a slow, obviously correct NumPy reference."""
import numpy as np
import pytest

from mkc_stream.kernels import OK, SINGULAR
from mkc_stream.kernels.correntropy import kernel_weights, mkc_loss, residuals
from mkc_stream.kernels.linalg import spd_solve
from mkc_stream.kernels.mstep import accumulate_normal, mstep_fixed_point


def problem(rng, N=60, m=2, n=3):
    X = rng.normal(size=(N, m, n))
    theta = rng.normal(size=n)
    Y = np.einsum("kmn,n->km", X, theta) + 0.1 * rng.normal(size=(N, m))
    Y[::7, 0] += 15.0
    return X, Y, theta


def test_residuals_weights_loss(rng):
    X, Y, th = problem(rng)
    sigma, d = np.array([1.5, 4.0]), np.array([0.3, 0.7])
    R = np.empty_like(Y)
    residuals(X, Y, th, R)
    R_ref = Y - np.einsum("kmn,n->km", X, th)
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-13)
    W = np.empty_like(Y)
    kernel_weights(R, sigma, d, W)
    np.testing.assert_allclose(W, np.exp(-(R_ref / d) ** 2 / (2 * sigma**2)), rtol=1e-11)
    J_ref = np.sum(sigma**2 * (1 - np.mean(np.exp(-(R_ref / d) ** 2 / (2 * sigma**2)), axis=0)))   # eq. (9)
    assert mkc_loss(R, sigma, d) == pytest.approx(J_ref, rel=1e-12)


def test_normal_equations_and_solve(rng):
    X, Y, _ = problem(rng)
    W = rng.uniform(0.1, 1.0, size=Y.shape)
    d = np.array([0.5, 2.0])
    A, b = np.empty((3, 3)), np.empty(3)
    accumulate_normal(X, Y, W, d, A, b)
    c = W / d**2
    A_ref = np.einsum("kmi,km,kmj->ij", X, c, X)   # sum_k X_k^T P W_k X_k, eq. (15)
    b_ref = np.einsum("kmi,km,km->i", X, c, Y)
    np.testing.assert_allclose(A, A_ref, rtol=1e-12)
    np.testing.assert_allclose(b, b_ref, rtol=1e-12)
    x, L, D = np.empty(3), np.zeros((3, 3)), np.empty(3)
    st, cond = spd_solve(A, b, x, L, D, 3)
    assert st == OK
    np.testing.assert_allclose(x, np.linalg.solve(A_ref, b_ref), rtol=1e-11)
    Dm = np.diag(1 / np.sqrt(np.diag(A_ref)))
    assert 1.0 <= cond <= np.linalg.cond(Dm @ A_ref @ Dm) * (1 + 1e-9)


def test_spd_solve_badly_scaled_features():
    # ellipsoid-like features of very different size: equilibration keeps full accuracy
    rng = np.random.default_rng(1)
    F = rng.normal(size=(500, 4)) * np.array([1e6, 1e3, 1.0, 1e-3])
    A = F.T @ F
    xt = rng.normal(size=4)
    b = A @ xt
    x, L, D = np.empty(4), np.zeros((4, 4)), np.empty(4)
    st, _ = spd_solve(A, b, x, L, D, 4)
    assert st == OK
    # b itself carries rounding of ~1e-16 x its largest term; compare with LAPACK's LU on the same b
    err_ours = np.abs(x - xt) / np.abs(xt)
    err_lu = np.abs(np.linalg.solve(A, b) - xt) / np.abs(xt)
    assert err_ours.max() < 1e-6
    assert err_ours.max() <= 10 * err_lu.max() + 1e-12


def test_spd_solve_reports_singular():
    A = np.array([[1.0, 1.0], [1.0, 1.0]])
    x, L, D = np.empty(2), np.zeros((2, 2)), np.empty(2)
    st, _ = spd_solve(A, np.ones(2), x, L, D, 2)
    assert st == SINGULAR
    A0 = np.zeros((2, 2))
    assert spd_solve(A0, np.ones(2), x, L, D, 2)[0] == SINGULAR


def naive_algorithm_1(X, Y, sigma, d, theta, iters):
    for _ in range(iters):
        R = Y - np.einsum("kmn,n->km", X, theta)
        W = np.exp(-(R / d) ** 2 / (2 * sigma**2))
        c = W / d**2
        theta = np.linalg.solve(np.einsum("kmi,km,kmj->ij", X, c, X), np.einsum("kmi,km,km->i", X, c, Y))
    return theta


def test_fixed_point_matches_naive_algorithm_1(rng):
    X, Y, th = problem(rng)
    sigma, d = np.array([2.0, 3.0]), np.array([0.2, 0.3])
    theta = np.zeros(3)
    N, m, n = X.shape
    ws = [np.empty((N, m)), np.empty((N, m)), np.empty((n, n)), np.empty(n), np.empty(n), np.zeros((n, n)), np.empty(n)]
    its, st, _ = mstep_fixed_point(X, Y, sigma, d, theta, 7, 0.0, *ws)
    assert its == 7
    np.testing.assert_allclose(theta, naive_algorithm_1(X, Y, sigma, d, np.zeros(3), 7), rtol=1e-10, atol=1e-12)
    # run to convergence: a fixed point of eq. (16) and robust to the channel-0 outliers
    its, st, _ = mstep_fixed_point(X, Y, sigma, d, theta, 200, 1e-12, *ws)
    assert st == OK
    np.testing.assert_allclose(naive_algorithm_1(X, Y, sigma, d, theta.copy(), 1), theta, rtol=1e-10, atol=1e-12)
    assert np.linalg.norm(theta - th) < 0.1
