"""The paper's examples as tests: a small fixed subset in CI, the full Table I under `-m slow`."""
import pathlib
import sys

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tools"))
import reproduce_paper as rp  # noqa: E402

from mkc_stream import MKCRegressor  # noqa: E402
from mkc_stream.baselines import LTSRegressor  # noqa: E402
from mkc_stream.batch import DEFAULT_A_FACTOR  # noqa: E402
from mkc_stream.kernels.estep import estep_channel  # noqa: E402


def errors(case, runs, names):
    est = rp.estimator_table(include_peers=False)
    rng = np.random.default_rng(rp.SEED + 1000 + case)
    out = {k: [] for k in names}
    for _ in range(runs):
        X, Y, th = rp.example2(rng, case)
        for k in names:
            out[k].append(np.linalg.norm(est[k](X, Y) - th))
    return {k: np.array(v) for k, v in out.items()}


def test_example2_case2_mkc_em_beats_lad_mkc_and_wls():
    e = errors(2, 40, ["WLS", "LAD", "MKC", "MKC-EM"])
    assert e["MKC-EM"].mean() < e["LAD"].mean() and e["MKC-EM"].mean() < e["MKC"].mean()
    assert e["MKC-EM"].mean() < 0.4 * e["WLS"].mean()


def test_example2_case1_gaussian_matches_wls():
    e = errors(1, 40, ["WLS", "MKC-EM"])
    assert e["MKC-EM"].mean() < 1.05 * e["WLS"].mean()


def profile_loglik(X, Y, theta):
    """MKC log-likelihood at theta with (sigma, d) maximised per channel (the E-step), a = DEFAULT_A_FACTOR max|e|."""
    R = Y - np.einsum("kmn,n->km", X, theta)
    N, total = R.shape[0], 0.0
    for i in range(R.shape[1]):
        e = np.ascontiguousarray(R[:, i])
        a = DEFAULT_A_FACTOR * np.abs(e).max()
        total -= N * estep_channel(e, N, a, 2.0, 1.0, 0.05, 1000.0, 1e-9 * a, a, 200, 1e-10, 0.0, np.zeros(3))[2]
    return total


def test_example2_case6_gap_is_the_models_bias_not_the_start():
    """Example 2, case 6. MKC-EM's case-6 mean error (0.094 over 200 runs, against 0.052 for the ML that
    knows the one-sided noise) is not the WLS start's doing: from WLS, from a high-breakdown (LTS) start
    and from the true theta the EM reaches the same fixed point (at N = 100 the LTS start moves the
    error by > 1e-4 in 2 of 400 case-6 draws, the case-6 mean by -0.0003 +- 0.0003), and that point
    has a higher MKC likelihood than the truth. The symmetric
    kernel's ML sits above the truth in the intercept because the U(0, 10)/U(0, 20) outliers within its
    reach pull one way; the bias does not shrink with N (intercept error 0.090 at N = 100, 0.069 at
    400, 0.074 at 2000), so no start can remove it. One N = 2000 draw (this seed: intercept +0.070;
    0.068-0.086 over six seeds): starts agree to 2e-8, the fixed point beats the truth by 18-27 nats.
    """
    X, Y, th = rp.example2(np.random.default_rng(rp.SEED + 1106), 6, N=2000)
    wls = MKCRegressor(sigma=20, d=[1, 2]).fit(X, Y)
    lts = MKCRegressor(theta0=LTSRegressor(channel_scale=[1, 2]).fit(X, Y).coef_).fit(X, Y)
    truth = MKCRegressor(theta0=th).fit(X, Y)
    assert wls.converged_ and lts.converged_ and truth.converged_
    np.testing.assert_allclose(lts.coef_, wls.coef_, atol=1e-6)
    np.testing.assert_allclose(truth.coef_, wls.coef_, atol=1e-6)
    assert 0.04 < wls.coef_[0] - th[0] < 0.11 and abs(wls.coef_[1] - th[1]) < 0.02
    assert profile_loglik(X, Y, wls.coef_) > profile_loglik(X, Y, th) + 5.0


def test_example1_sigma_sweep_shape():
    logs, rmse, wls = rp.sigma_sweep(runs=15, n_sigma=9)
    j = int(np.argmin(rmse))
    assert 0 < j < len(logs) - 1                  # falls, then rises (Fig. 4, Proposition 1)
    assert rmse[j] < 0.5 * wls
    assert rmse[-1] == pytest.approx(wls, rel=0.05)  # coincides with WLS for large sigma (Theorem 1)


def test_fig3_mkc_likelihood_never_below_gaussian():
    lik = rp.likelihood_comparison(N=3000)
    assert all(a >= b - 1e-9 for a, b in zip(lik["ll_cl"], lik["ll_wls"]))
    assert lik["ll_cl"][-1] - lik["ll_wls"][-1] > lik["ll_cl"][1] - lik["ll_wls"][1] > 0


@pytest.mark.slow
def test_table1_full_acceptance():
    """Table I with 200 runs per case and every estimator (about 25 minutes on 2 shared cores).

    The paper's MKC-EM means in cases 3 and 4 (0.0380, 0.0418) lie below what the maximum-likelihood
    estimator that KNOWS the true noise mixture reaches on this setup (0.042, 0.047): no estimator
    can match them, so there we hold MKC-EM to within 5% of that oracle instead.
    """
    res = rp.table1(200, include_peers=True, oracle=True, progress=False)
    for case in (1, 2, 5):
        assert res[case]["MKC-EM"]["mean"] <= 1.10 * rp.PAPER_TABLE_I[case][1]["MKC-EM"], case
    for case in (3, 4):
        assert res[case]["MKC-EM"]["mean"] <= 1.05 * res[case]["oracle-MLE"]["mean"], case
        assert res[case]["oracle-MLE"]["mean"] > rp.PAPER_TABLE_I[case][1]["MKC-EM"], case
    for case in (1, 2, 3, 4, 5):
        em = res[case]["MKC-EM"]["mean"]
        assert em <= res[case]["LAD"]["mean"] and em <= res[case]["MKC"]["mean"], case
        assert em <= 1.03 * res[case]["RLM-Tukey"]["mean"], case      # a tie within Monte Carlo noise
    assert res[1]["MKC-EM"]["mean"] <= 1.05 * res[1]["WLS"]["mean"]
    assert res[6]["MKC-EM"]["mean"] < res[6]["LAD"]["mean"] and res[6]["MKC-EM"]["mean"] < res[6]["RLM-Tukey"]["mean"]
