"""MKCRegressor / WLSRegressor: Theorem 1, EM behaviour, API shapes, bad input."""
import numpy as np
import pytest

from mkc_stream import MKCInputError, MKCRegressor, WLSRegressor, mkc_loss


def example2(rng, N=100, p1=0.8, p2=0.8):
    """Example 2 of the paper, eqs. (34)-(35), x ~ U(-5, 5)."""
    x = rng.uniform(-5, 5, N)
    Xk = np.stack([np.ones(N), x], 1)
    X = np.stack([Xk, Xk], 1)
    v1 = np.where(rng.random(N) < p1, rng.normal(0, 0.5, N), rng.uniform(-10, 10, N))
    v2 = np.where(rng.random(N) < p2, rng.normal(0, 1.0, N), rng.uniform(-20, 20, N))
    return X, X @ np.ones(2) + np.stack([v1, v2], 1), np.ones(2)


def test_theorem_1_loss_limit(rng):
    R = rng.normal(size=(50, 2)) * [0.5, 3.0]
    d = np.array([0.7, 1.1])
    J_wls = np.sum(np.mean((R / d) ** 2, axis=0)) / 2          # eq. (10)
    errs = [abs(mkc_loss(R, s, d) - J_wls) / J_wls for s in (10.0, 100.0, 1e4, 1e6)]
    # eq. (11)-(12): the gap closes like 1/sigma^2 (next Taylor term e^4 / (8 sigma^2))
    assert errs[0] > errs[1] > errs[2] > errs[3] and errs[3] < 1e-11
    assert errs[1] / errs[2] == pytest.approx(1e4, rel=1e-3)
    assert mkc_loss(R, np.inf, d) == pytest.approx(J_wls, rel=1e-14)


def test_theorem_1_solution_limit(rng):
    X, Y, _ = example2(rng)
    wls = WLSRegressor(d=[1, 2]).fit(X, Y)
    P = np.diag([1.0, 0.25])
    A = np.einsum("kmi,mn,knj->ij", X, P, X)
    b = np.einsum("kmi,mn,kn->i", X, P, Y)
    np.testing.assert_allclose(wls.coef_, np.linalg.solve(A, b), rtol=1e-12)   # eq. (7)
    big = MKCRegressor(em=False, sigma=1e7, d=[1, 2]).fit(X, Y)
    np.testing.assert_allclose(big.coef_, wls.coef_, rtol=1e-9)


def test_mkc_em_is_robust_and_learns_per_channel_kernels():
    rng = np.random.default_rng(7)
    X, Y, th = example2(rng, N=400, p1=0.7, p2=1.0)
    em = MKCRegressor(sigma=20, d=[1, 2]).fit(X, Y)
    wls = WLSRegressor(d=[1, 2]).fit(X, Y)
    assert np.linalg.norm(em.coef_ - th) < 0.05 < np.linalg.norm(wls.coef_ - th)
    # channel 1 has the heavy tail -> small sigma; channel 2 is Gaussian -> wide kernel (Fig. 6(a))
    assert em.sigma_[0] < 4 < em.sigma_[1]
    assert em.d_[0] == pytest.approx(0.5, rel=0.25) and em.d_[1] == pytest.approx(1.0, rel=0.25)
    assert em.converged_ and 1 <= em.n_iter_ <= 10
    assert em.weights_.shape == (400, 2)
    # outliers of channel 1 get small weights
    r1 = np.abs(Y[:, 0] - X[:, 0] @ th)
    assert em.weights_[r1 > 5, 0].max() < 0.05 and np.median(em.weights_[r1 < 0.5, 0]) > 0.9
    assert em.history_["sigma"].shape == (em.n_iter_ + 1, 2)


def test_gaussian_case_matches_wls():
    rng = np.random.default_rng(11)
    errs_em, errs_wls = [], []
    for _ in range(30):
        X, Y, th = example2(rng, p1=1.0, p2=1.0)
        errs_em.append(np.linalg.norm(MKCRegressor(sigma=20, d=[1, 2]).fit(X, Y).coef_ - th))
        errs_wls.append(np.linalg.norm(WLSRegressor(d=[1, 2]).fit(X, Y).coef_ - th))
    assert np.mean(errs_em) < 1.1 * np.mean(errs_wls)


def test_single_channel_shapes_and_defaults(rng):
    x = 8 * np.sin(0.04 * np.pi * np.arange(300))                     # Example 1, eq. (32)-(33)
    v = np.where(rng.random(300) < 0.9, rng.normal(0, 0.5, 300), rng.uniform(-20, 20, 300))
    y = 2.0 * x + v
    m = MKCRegressor().fit(x[:, None], y)
    assert m.coef_.shape == (1,) and m.sigma_.shape == (1,) and m.weights_.shape == (300,)
    assert abs(m.coef_[0] - 2.0) < 0.02
    np.testing.assert_allclose(m.predict(x[:, None]), 2.0 * x, atol=0.2)
    assert m.residuals(x[:, None], y).shape == (300,)
    assert MKCRegressor(sigma=3.0).get_params()["sigma"] == 3.0


def test_fixed_mkc_needs_sigma(rng):
    X, Y, _ = example2(rng)
    with pytest.raises(MKCInputError, match="sigma"):
        MKCRegressor(em=False).fit(X, Y)


@pytest.mark.parametrize("mutate,match", [
    (lambda X, Y: (X, np.where(np.arange(Y.size).reshape(Y.shape) == 5, np.nan, Y)), "NaN"),
    (lambda X, Y: (X[:0], Y[:0]), "too few"),
    (lambda X, Y: (np.concatenate([X, X[..., :1]], axis=2), Y), "rank deficient"),
    (lambda X, Y: (X, Y[:, :1]), "shape"),
])
def test_bad_input_is_a_clear_error(rng, mutate, match):
    X, Y, _ = example2(rng)
    Xb, Yb = mutate(X, Y)
    with pytest.raises(MKCInputError, match=match):
        MKCRegressor().fit(Xb, Yb)
    with pytest.raises(MKCInputError, match=match):
        WLSRegressor().fit(Xb, Yb)


def test_bad_parameters(rng):
    X, Y, _ = example2(rng)
    with pytest.raises(MKCInputError):
        MKCRegressor(sigma=[1.0, 2.0, 3.0]).fit(X, Y)
    with pytest.raises(MKCInputError):
        MKCRegressor(d=-1.0).fit(X, Y)
    with pytest.raises(MKCInputError):
        MKCRegressor(sigma_bounds=(2.0, 1.0)).fit(X, Y)


def test_exact_fit_stays_finite():
    X = np.stack([np.ones(50), np.arange(50.0)], 1)
    y = X @ np.array([3.0, -2.0])
    m = MKCRegressor().fit(X, y)
    np.testing.assert_allclose(m.coef_, [3.0, -2.0], rtol=1e-9)
    assert np.isfinite(m.sigma_).all() and np.isfinite(m.d_).all() and np.isfinite(m.weights_).all()
