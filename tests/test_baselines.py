"""The seeds' comparison estimators (mkc_stream.baselines): accuracy, robustness, references, API."""
import sys
import warnings

import numpy as np
import pytest
from scipy.optimize import check_grad, minimize

from mkc_stream import MKCInputError
from mkc_stream.baselines import (BASELINES, HuberRegressor, LADRegressor, LeastEntropyLikeRegressor, LMSRegressor,
                                  LTSRegressor, RANSACRegressor, RobustKernelRegressor, entropy_like)
from mkc_stream.baselines.lad import lad_fit, lad_primal
from mkc_stream.baselines.lel import _h_and_grad, multistart_points
from mkc_stream.baselines.r3 import huber_eps_loss, r3_fit, rbf_kernel

THETA = np.array([1.0, -2.0, 0.5, 3.0])
SIGMA = 0.05
ROBUST = ["lad", "lel", "lms", "lts", "ransac", "huber", "r3-huber", "r3-huber-eps"]
SKLEARN_BASED = ["ridge", "lasso", "ransac", "huber"]


def make_data(seed=0, N=200, frac=0.0):
    """y = X theta + N(0, 0.05^2) with a constant column; frac of the rows shifted up by U(8, 20)."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([np.ones(N), rng.normal(size=(N, 3))])
    y = X @ THETA + SIGMA * rng.normal(size=N)
    out = np.zeros(N, dtype=bool)
    out[rng.permutation(N)[: int(round(frac * N))]] = True
    y[out] += rng.uniform(8, 20, out.sum())     # one-sided gross errors: the hard case for LS
    return X, y, out


def make_two_channel(seed=3, N=150, frac=0.2):
    """The MKC paper's layout: one X_k shared by 2 channels, channel 2 twice as noisy."""
    rng = np.random.default_rng(seed)
    Xk = np.column_stack([np.ones(N), rng.normal(size=(N, 3))])
    X = np.stack([Xk, Xk], axis=1)                              # (N, 2, 4)
    Y = X @ THETA + rng.normal(size=(N, 2)) * [SIGMA, 2 * SIGMA]
    bad = rng.random((N, 2)) < frac
    Y[bad] += rng.uniform(8, 20, bad.sum())
    return X, Y


def err(est):
    return float(np.linalg.norm(est.coef_ - THETA))


# ---------------------------------------------------------------------------------------- registry / API

def test_registry_names_and_no_arg_construction():
    assert set(BASELINES) == {"lad", "ridge", "lasso", "lel", "lms", "lts", "ransac", "huber", "r3-huber",
                              "r3-huber-eps"}
    for cls in BASELINES.values():
        est = cls()
        params = est.get_params()
        assert "channel_scale" in params and params["channel_scale"] is None
        assert type(est)(**params).get_params() == params      # __init__ only stores its arguments


def test_sklearn_clone_round_trip():
    clone = pytest.importorskip("sklearn.base").clone

    for cls in BASELINES.values():
        est = cls(channel_scale=[1.0, 2.0])
        assert clone(est).get_params() == est.get_params()


@pytest.mark.parametrize("name", sorted(BASELINES))
def test_recovers_theta_on_clean_data(name):
    X, y, _ = make_data(0)
    est = BASELINES[name]()
    assert est.fit(X, y) is est
    assert est.coef_.shape == (4,)
    # LEL minimises a nearly flat H on outlier-free Gaussian data and fits the noise (paper, Table 2)
    tol = 0.2 if name == "lel" else 0.06
    assert err(est) < tol
    np.testing.assert_allclose(est.predict(X), X @ est.coef_ + getattr(est, "intercept_", 0.0))


@pytest.mark.parametrize("name", ROBUST)
def test_robust_with_20_percent_gross_outliers(name):
    X, y, _ = make_data(0, frac=0.2)
    ls = np.linalg.lstsq(X, y, rcond=None)[0]
    assert np.linalg.norm(ls - THETA) > 2.0                       # least squares breaks
    est = BASELINES[name]().fit(X, y)
    tol = 0.15 if name == "lel" else 0.1
    assert err(est) < tol


@pytest.mark.parametrize("name", ["ridge", "lasso"])
def test_penalised_wrappers_break_down_and_shrink(name):
    X, y, _ = make_data(0, frac=0.2)
    assert err(BASELINES[name]().fit(X, y)) > 2.0
    small, big = BASELINES[name](alpha=1e-6).fit(X, y), BASELINES[name](alpha=50.0).fit(X, y)
    assert np.linalg.norm(big.coef_) < np.linalg.norm(small.coef_)


# ---------------------------------------------------------------------------------------- multi-channel

@pytest.mark.parametrize("name", sorted(BASELINES))
def test_channel_scale_equals_scaled_stacked_problem(name):
    X, Y = make_two_channel()
    d = np.array([1.0, 2.0])
    multi = BASELINES[name](channel_scale=d).fit(X, Y)
    A = (X / d[None, :, None]).reshape(-1, 4)                    # sample-major stacking
    b = (Y / d).reshape(-1)
    single = BASELINES[name]().fit(A, b)
    np.testing.assert_allclose(multi.coef_, single.coef_, rtol=1e-7, atol=1e-9)
    for attr in ("weights_", "inlier_mask_"):
        if hasattr(multi, attr):
            assert getattr(multi, attr).shape == (150, 2)
            assert getattr(single, attr).shape == (300,)
            np.testing.assert_array_equal(getattr(multi, attr).reshape(-1), getattr(single, attr))
    assert multi.predict(X).shape == (150, 2)
    assert multi.residuals(X, Y).shape == (150, 2) and single.residuals(A, b).shape == (300,)


@pytest.mark.parametrize("name", ROBUST)
def test_multichannel_robust(name):
    X, Y = make_two_channel()
    est = BASELINES[name](channel_scale=[1, 2]).fit(X, Y)
    assert err(est) < (0.15 if name == "lel" else 0.1)


# ---------------------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("name", sorted(BASELINES))
def test_bad_input_raises(name):
    X, y, _ = make_data(1, N=40)
    cls = BASELINES[name]
    Xn = X.copy()
    Xn[5, 2] = np.nan
    with pytest.raises(MKCInputError, match="NaN"):
        cls().fit(Xn, y)
    yn = y.copy()
    yn[3] = np.inf
    with pytest.raises(MKCInputError, match="NaN or inf"):
        cls().fit(X, yn)
    Xr = np.column_stack([X, X[:, 1] - 2 * X[:, 2]])               # rank 4 < 5 unknowns
    with pytest.raises(MKCInputError, match="rank deficient"):
        cls().fit(Xr, y)
    with pytest.raises(MKCInputError, match="too few samples"):
        cls().fit(X[:3], y[:3])
    with pytest.raises(MKCInputError):
        cls().fit(X, y[:-1])
    X3, Y2 = make_two_channel(N=30)
    with pytest.raises(MKCInputError, match="channel_scale"):
        cls(channel_scale=[1.0, -1.0]).fit(X3, Y2)
    with pytest.raises(MKCInputError, match="channel_scale"):
        cls(channel_scale=[1.0, 2.0, 3.0]).fit(X3, Y2)


@pytest.mark.parametrize("name", SKLEARN_BASED)
def test_missing_sklearn_names_the_extra(name, monkeypatch):
    X, y, _ = make_data(0, N=30)
    est = BASELINES[name]()                                      # construction never imports sklearn
    monkeypatch.setitem(sys.modules, "sklearn", None)
    monkeypatch.setitem(sys.modules, "sklearn.linear_model", None)
    with pytest.raises(ImportError, match=r"mkc-stream\[baselines\]"):
        est.fit(X, y)


def test_core_estimators_need_no_sklearn(monkeypatch):
    X, y, _ = make_data(0, N=60, frac=0.1)
    monkeypatch.setitem(sys.modules, "sklearn", None)
    monkeypatch.setitem(sys.modules, "sklearn.linear_model", None)
    for name in ("lad", "lel", "lms", "lts", "r3-huber", "r3-huber-eps"):
        assert err(BASELINES[name]().fit(X, y)) < 0.2


# ---------------------------------------------------------------------------------------- LAD

def test_lad_matches_statsmodels_quantreg():
    sm = pytest.importorskip("statsmodels.api")
    X, y, _ = make_data(2, frac=0.2)
    lad = LADRegressor().fit(X, y)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        q = sm.QuantReg(y, X).fit(q=0.5, max_iter=5000, p_tol=1e-10)
    ref = np.abs(y - X @ q.params).sum()
    assert lad.converged_
    assert lad.objective_ == pytest.approx(np.abs(y - X @ lad.coef_).sum(), rel=1e-12)
    assert lad.objective_ <= ref * (1 + 1e-9)                    # exact LP vs IRLS: never worse
    assert lad.objective_ == pytest.approx(ref, rel=1e-6)


def test_lad_is_a_minimum_and_primal_fallback_agrees():
    X, y, _ = make_data(4, N=80, frac=0.2)
    theta, obj, _, ok = lad_fit(X, y)
    rng = np.random.default_rng(0)
    for _ in range(50):
        d = rng.normal(size=4) * 1e-4
        assert np.abs(y - X @ (theta + d)).sum() >= obj - 1e-12
    # an L1 fit interpolates at least n rows
    assert np.sum(np.abs(y - X @ theta) < 1e-8) >= 4
    _, obj_primal, _, ok_primal = lad_primal(X, y)
    assert ok and ok_primal and obj_primal == pytest.approx(obj, rel=1e-9)


# ---------------------------------------------------------------------------------------- Huber

def test_huber_satisfies_its_estimating_equation_and_matches_rlm():
    sm = pytest.importorskip("statsmodels.api")
    X, y, out = make_data(0, frac=0.2)
    h = HuberRegressor().fit(X, y)
    assert h.converged_
    r = y - X @ h.coef_
    # sum_i psi(r_i / s) x_i = 0 with psi = clip(., -eps, eps), i.e. X^T (w * r) = 0
    psi = np.clip(r / h.scale_, -1.35, 1.35)
    assert np.abs(X.T @ psi).max() < 1e-4 * np.abs(X).sum(0).max()
    np.testing.assert_allclose(h.weights_ * r / h.scale_, psi, atol=1e-12)
    # scale_ is Owen's concomitant sigma (E[min(z^2, eps^2)] = 1, about 0.85 x the Gaussian sd), so
    # only ~3/4 of the clean rows fall inside eps * scale_
    assert not h.inlier_mask_[out].any() and h.inlier_mask_[~out].mean() > 0.7
    rlm = sm.RLM(y, X, M=sm.robust.norms.HuberT(t=1.35)).fit()   # IRLS with a MAD scale
    np.testing.assert_allclose(h.coef_, rlm.params, atol=0.02)


# ---------------------------------------------------------------------------------------- LMS / LTS / RANSAC

def test_lms_objective_is_its_order_statistic():
    X, y, out = make_data(1, frac=0.2)
    lms = LMSRegressor().fit(X, y)
    M, n = X.shape
    h = M // 2 + (n + 1) // 2
    r2 = np.sort((y - X @ lms.coef_) ** 2)
    assert lms.objective_ == pytest.approx(r2[h - 1], rel=1e-12)
    ls = np.linalg.lstsq(X, y, rcond=None)[0]
    assert lms.objective_ < np.sort((y - X @ ls) ** 2)[h - 1]
    # raw scale: the h-subset holds 5/8 of the clean rows when 20% are outliers, so it overshoots
    assert SIGMA < lms.scale_ < 2 * SIGMA
    assert not lms.inlier_mask_[out].any()
    # same seed, same answer; another seed, another random search
    assert np.array_equal(LMSRegressor().fit(X, y).coef_, lms.coef_)


def test_lts_concentration_reaches_at_most_the_truth_trimmed_sum():
    X, y, out = make_data(1, frac=0.2)
    lts = LTSRegressor().fit(X, y)
    M, n = X.shape
    h = (M + n + 1) // 2
    assert lts.h_ == h and lts.support_.sum() == h and lts.converged_
    r2 = np.sort((y - X @ lts.coef_) ** 2)
    assert lts.objective_ == pytest.approx(r2[:h].sum(), rel=1e-12)
    assert lts.objective_ <= np.sort((y - X @ THETA) ** 2)[:h].sum() * (1 + 1e-12)
    # the C-step fixed point: LS on its own support reproduces coef_
    np.testing.assert_allclose(np.linalg.lstsq(X[lts.support_], y[lts.support_], rcond=None)[0], lts.coef_,
                               rtol=1e-9, atol=1e-12)
    assert not lts.support_[out].any()
    assert SIGMA < lts.scale_ < 2 * SIGMA                        # raw (unreweighted) scale overshoots
    assert LTSRegressor(h=0.9).fit(X, y).h_ == 180


def test_ransac_flags_the_outliers():
    X, y, out = make_data(2, frac=0.2)
    est = RANSACRegressor().fit(X, y)
    assert est.inlier_mask_.shape == (200,)
    assert not est.inlier_mask_[out].any() and est.inlier_mask_[~out].mean() > 0.95
    assert 2 * SIGMA < est.residual_threshold_ < 4 * SIGMA     # 2.5 x a MAD scale of the LAD residuals
    assert np.array_equal(RANSACRegressor().fit(X, y).coef_, est.coef_)


# ---------------------------------------------------------------------------------------- LEL

def test_entropy_like_properties():
    assert entropy_like(np.zeros(7)) == 0.0                     # eq. (42), D = 0
    assert entropy_like([0, 0, 3.0, 0]) == 0.0                  # eq. (44)
    assert entropy_like([2.0, -2.0, 2.0, 2.0, -2.0]) == pytest.approx(1.0)   # eq. (45)
    r = np.random.default_rng(0).standard_t(2, 100)
    assert 0 < entropy_like(r) < 1
    assert entropy_like(5 * r) == pytest.approx(entropy_like(r), rel=1e-12)  # scale invariance (Sec. 4.1)


def test_lel_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(60, 3))
    Q, _ = np.linalg.qr(A)
    b = rng.normal(size=60)
    for _ in range(3):
        z = rng.normal(size=3)
        f = lambda z: _h_and_grad(z, Q, b, np.log(60))[0]
        g = lambda z: _h_and_grad(z, Q, b, np.log(60))[1]
        assert check_grad(f, g, z) < 1e-6 * max(1.0, np.linalg.norm(g(z)))


def test_lel_multistart_rule_and_objective():
    X, y, _ = make_data(0, frac=0.2)
    lel = LeastEntropyLikeRegressor().fit(X, y)
    ls = np.linalg.lstsq(X, y, rcond=None)[0]
    S = lel.starts_
    # eqs. (50)-(51): theta_1 = LS, mutually orthogonal, all of norm ||theta_LS||
    np.testing.assert_allclose(S[0], ls, rtol=1e-10)
    G = S @ S.T
    np.testing.assert_allclose(G, np.eye(4) * (ls @ ls), atol=1e-9 * (ls @ ls))
    assert lel.solutions_.shape == (4, 4) and lel.objectives_.shape == (4,)
    assert lel.objective_ == pytest.approx(entropy_like(y - X @ lel.coef_), rel=1e-12)
    assert lel.objective_ <= lel.start_objective_ == pytest.approx(entropy_like(y - X @ ls))
    assert lel.objective_ == np.min(lel.objectives_[~lel.escaped_])
    one = LeastEntropyLikeRegressor(multistart=False).fit(X, y)
    assert one.starts_.shape == (1, 4) and one.objective_ >= lel.objective_ - 1e-12
    nm = LeastEntropyLikeRegressor(method="Nelder-Mead", multistart=False).fit(X, y)
    assert nm.objective_ <= nm.start_objective_


def test_lel_multistart_points_edge_cases():
    P = multistart_points(np.array([0.0, 3.0, 4.0]))
    np.testing.assert_allclose(P @ P.T, 25 * np.eye(3), atol=1e-12)
    assert multistart_points(np.zeros(2)).shape == (2, 2)


def test_lel_returns_exact_fit_and_does_not_escape_on_clean_data():
    X, _, _ = make_data(0, N=30)
    exact = LeastEntropyLikeRegressor().fit(X, X @ THETA)
    np.testing.assert_allclose(exact.coef_, THETA, rtol=1e-10)
    assert exact.objective_ == 0.0
    X, y, _ = make_data(0)
    lel = LeastEntropyLikeRegressor().fit(X, y)
    assert np.linalg.norm(X @ lel.coef_) <= 10 * np.linalg.norm(y)


# ---------------------------------------------------------------------------------------- R3

def _r3_primal(X, y, lam, m, eps, intercept):
    def E(p):
        w, b = (p[:-1], p[-1]) if intercept else (p, 0.0)
        return huber_eps_loss(X @ w + b - y, m, eps).sum() + lam * w @ w
    p0 = np.zeros(X.shape[1] + intercept)
    return minimize(E, p0, method="BFGS", options={"gtol": 1e-11, "maxiter": 10000}), E


@pytest.mark.parametrize("loss,eps", [("huber", 0.0), ("huber-eps", 0.15)])
@pytest.mark.parametrize("intercept", [True, False])
def test_r3_linear_matches_direct_minimisation(loss, eps, intercept):
    rng = np.random.default_rng(5)
    N = 40
    X = rng.normal(size=(N, 3))
    y = X @ [1.0, -1.0, 2.0] + 0.7 + 0.2 * rng.normal(size=N)
    y[:8] += rng.uniform(3, 6, 8)
    lam, m = 0.5, 0.3
    est = RobustKernelRegressor(loss=loss, lam=lam, m=m, epsilon=eps if loss == "huber-eps" else None,
                                fit_intercept=intercept).fit(X, y)
    ref, E = _r3_primal(X, y, lam, m, eps, intercept)
    p = np.append(est.coef_, est.intercept_) if intercept else est.coef_
    assert est.converged_ and est.objective_ == pytest.approx(E(p), rel=1e-12)
    assert est.objective_ <= ref.fun * (1 + 1e-10)
    np.testing.assert_allclose(p, ref.x, atol=1e-5)
    if intercept:
        # the representer of the linear kernel: w = X^T alpha with 1^T alpha = 0 (the b row of (*))
        np.testing.assert_allclose(X.T @ est.dual_coef_, est.coef_, atol=1e-9)
        assert abs(est.dual_coef_.sum()) < 1e-9
    np.testing.assert_allclose(est.predict(X), X @ est.coef_ + est.intercept_)


def test_r3_kernel_form_equals_linear_form():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(30, 3))
    y = A @ [0.5, 1.0, -1.0] + 1.0 + 0.1 * rng.normal(size=30)
    y[:5] -= 4
    for eps in (0.0, 0.05):
        lin = r3_fit(y, 0.2, eps, 0.3, A=A)
        ker = r3_fit(y, 0.2, eps, 0.3, K=A @ A.T)
        assert lin["converged"] and ker["converged"]
        assert ker["objective"] == pytest.approx(lin["objective"], rel=1e-10)
        np.testing.assert_allclose(A.T @ ker["coef"], lin["coef"], atol=1e-8)
        assert ker["b"] == pytest.approx(lin["b"], abs=1e-8)


def test_r3_rbf_matches_direct_minimisation_and_resists_outliers():
    rng = np.random.default_rng(7)
    N = 60
    x = np.sort(rng.uniform(-10, 10, N))
    y = np.sinc(x / np.pi) + 0.05 * rng.normal(size=N)
    bad = rng.permutation(N)[:12]
    y[bad] += rng.uniform(1, 3, 12)
    X = x[:, None]
    lam, m, gamma = 0.05, 0.1, 0.3
    est = RobustKernelRegressor(kernel="rbf", lam=lam, m=m, gamma=gamma).fit(X, y)
    K = rbf_kernel(X, X, gamma)

    def E(p):
        a, b = p[:-1], p[-1]
        return huber_eps_loss(K @ a + b - y, m).sum() + lam * a @ K @ a

    ref = minimize(E, np.zeros(N + 1), method="BFGS", options={"gtol": 1e-9, "maxiter": 20000})
    assert est.converged_
    assert est.objective_ == pytest.approx(E(np.append(est.dual_coef_, est.intercept_)), rel=1e-12)
    assert est.objective_ <= ref.fun * (1 + 1e-8)
    np.testing.assert_allclose(est.predict(X), K @ ref.x[:-1] + ref.x[-1], atol=1e-3)
    # predict() on new points uses the stored training rows
    xt = np.linspace(-9, 9, 50)[:, None]
    truth = np.sinc(xt[:, 0] / np.pi)
    rls = RobustKernelRegressor(kernel="rbf", lam=lam, m=1e6, gamma=gamma).fit(X, y)   # m -> inf: RLS
    mse_r3, mse_rls = np.mean((est.predict(xt) - truth) ** 2), np.mean((rls.predict(xt) - truth) ** 2)
    assert est.predict(xt).shape == (50,) and mse_r3 < mse_rls / 3
    auto = RobustKernelRegressor(kernel="rbf", lam=lam).fit(X, y)
    assert auto.m_ > 0 and np.mean((auto.predict(xt) - truth) ** 2) < mse_rls


def test_r3_parameters_and_outputs():
    X, y, out = make_data(0, frac=0.2)
    est = BASELINES["r3-huber"]().fit(X, y)
    # m_ = 1.345 x a MAD scale, which the 20% outliers inflate somewhat
    assert est.intercept_ == 0.0 and 1.345 * SIGMA < est.m_ < 3 * SIGMA
    assert not est.inlier_mask_[out].any() and est.weights_[out].max() < 0.05
    eps = BASELINES["r3-huber-eps"]().fit(X, y)
    assert eps.epsilon_ == pytest.approx(0.5 / 1.345 * eps.m_)
    with pytest.raises(ValueError, match="loss"):
        RobustKernelRegressor(loss="tukey").fit(X, y)
    with pytest.raises(ValueError, match="epsilon"):
        RobustKernelRegressor(loss="huber", epsilon=0.1).fit(X, y)
    with pytest.raises(ValueError, match="lam"):
        RobustKernelRegressor(kernel="rbf", lam=0.0).fit(X, y)
    # lam = 0 with the linear kernel is Huber regression with a fixed threshold
    plain = RobustKernelRegressor(lam=0.0, m=0.1, fit_intercept=False).fit(X, y)
    assert err(plain) < 0.1
