"""E-step (Algorithm 2): the objective (30)-(31) and the bounded BFGS that minimises it."""
import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import minimize

from mkc_stream.kernels import OK
from mkc_stream.kernels.estep import estep_channel, estep_objective

LO, HI = 0.05, 1000.0


def nll_reference(sigma, d, e, a):
    """-(1/N) sum log p(e_k), p of eq. (17) truncated to [-a, a], with Z by scipy quad."""
    f = lambda u: math.exp(-sigma**2 * (1 - math.exp(-u * u / (2 * sigma**2))))  # noqa: E731
    A = a / d
    Z = 2 * quad(f, 0, A, points=[min(A, 1.0), min(A, sigma)], limit=400, epsabs=0, epsrel=1e-13)[0]
    return math.log(d) + math.log(Z) + sigma**2 * np.mean(1 - np.exp(-e**2 / (2 * d * d * sigma**2)))


def mixture(rng, N=400, p=0.8, sd=0.5, half=10.0):
    z = rng.random(N) < p
    return np.where(z, rng.normal(0, sd, N), rng.uniform(-half, half, N))


def test_objective_value_and_gradient(rng):
    e = mixture(rng)
    a = 1.5 * np.abs(e).max()
    for sigma, d in [(0.3, 2.0), (2.0, 0.5), (8.0, 1.0)]:
        F, gs, gd = estep_objective(math.log(sigma), math.log(d), e, e.size, a, 0.0)
        assert F == pytest.approx(nll_reference(sigma, d, e, a), rel=1e-10)
        h = 1e-6
        fs = (estep_objective(math.log(sigma) + h, math.log(d), e, e.size, a, 0.0)[0] - estep_objective(math.log(sigma) - h, math.log(d), e, e.size, a, 0.0)[0]) / (2 * h)
        fd = (estep_objective(math.log(sigma), math.log(d) + h, e, e.size, a, 0.0)[0] - estep_objective(math.log(sigma), math.log(d) - h, e, e.size, a, 0.0)[0]) / (2 * h)
        assert gs == pytest.approx(fs, rel=1e-5, abs=1e-8)
        assert gd == pytest.approx(fd, rel=1e-5, abs=1e-8)


@pytest.mark.parametrize("p,sd,half", [(0.8, 0.5, 10.0), (0.6, 1.0, 20.0), (0.95, 0.2, 5.0)])
def test_reaches_the_same_optimum_as_scipy(p, sd, half):
    rng = np.random.default_rng(int(100 * p))
    e = mixture(rng, 600, p, sd, half)
    a = 1.5 * np.abs(e).max()
    dlo, dhi = 1e-6 * a, a
    s, d, F, its, st = estep_channel(e, e.size, a, 20.0, 2.0, LO, HI, dlo, dhi, 100, 1e-9, 0.0, np.zeros(3))
    assert st == OK
    fun = lambda z: estep_objective(z[0], z[1], e, e.size, a, 0.0)[0]  # noqa: E731
    jac = lambda z: np.array(estep_objective(z[0], z[1], e, e.size, a, 0.0)[1:])  # noqa: E731
    best = min((minimize(fun, z0, jac=jac, method="L-BFGS-B", bounds=[(math.log(LO), math.log(HI)), (math.log(dlo), math.log(dhi))],
                         options={"ftol": 1e-15, "gtol": 1e-12}) for z0 in ([3.0, 0.7], [0.0, -1.0], [1.0, 0.0])), key=lambda r: r.fun)
    assert F <= best.fun + 1e-9
    assert math.log(s) == pytest.approx(best.x[0], abs=1e-3)
    assert math.log(d) == pytest.approx(best.x[1], abs=1e-3)
    # the head width d sits near the inlier std and the tail makes sigma moderate
    assert 0.5 * sd < d < 1.5 * sd and 0.5 < s < 10


def test_warm_start_converges_immediately(rng):
    e = mixture(rng)
    a = 1.5 * np.abs(e).max()
    s, d, F, its, st = estep_channel(e, e.size, a, 20.0, 2.0, LO, HI, 1e-6 * a, a, 100, 1e-9, 0.0, np.zeros(3))
    s2, d2, F2, its2, st2 = estep_channel(e, e.size, a, s, d, LO, HI, 1e-6 * a, a, 100, 1e-9, 0.0, np.zeros(3))
    assert st2 == OK and its2 <= 2 and its2 < its
    assert s2 == pytest.approx(s, rel=1e-6) and d2 == pytest.approx(d, rel=1e-6)


def test_gaussian_residuals_push_sigma_up(rng):
    e = rng.normal(0, 1.3, 5000)
    a = 1.5 * np.abs(e).max()
    s, d, F, its, st = estep_channel(e, e.size, a, 1.0, 1.0, LO, HI, 1e-6 * a, a, 200, 1e-9, 0.0, np.zeros(3))
    # Gaussian limit (Corollary 1): the tail floor exp(-sigma^2) is invisible (< 1e-7 of the peak)
    assert s > 4
    assert d == pytest.approx(1.3, rel=0.05)
    assert F <= estep_objective(math.log(HI), math.log(d), e, e.size, a, 0.0)[0] + 1e-12


def test_safe_on_degenerate_input():
    # all residuals zero, one huge outlier, uniform data: bounded, finite, never NaN
    for e in (np.zeros(50), np.r_[np.zeros(49), 1e12], np.linspace(-1, 1, 200)):
        a = max(np.abs(e).max(), 1e-12)
        s, d, F, its, st = estep_channel(e, e.size, a, 20.0, 1.0, LO, HI, 1e-6 * a, a, 100, 1e-9, 0.0, np.zeros(3))
        assert np.isfinite([s, d, F]).all()
        assert LO * (1 - 1e-12) <= s <= HI * (1 + 1e-12)
        assert 1e-6 * a * (1 - 1e-12) <= d <= a * (1 + 1e-12)
    # uniform residuals: the likelihood prefers the flattest pdf -> sigma at its lower bound, not 0
    assert s == pytest.approx(LO, rel=1e-9)


def test_bad_input_returns_status_not_nan():
    s, d, F, its, st = estep_channel(np.ones(3), 0, 1.0, 2.0, 1.0, LO, HI, 1e-6, 1.0, 10, 1e-9, 0.0, np.zeros(3))
    assert st != OK and (s, d) == (2.0, 1.0)


def test_sigma_pull_is_a_log_sigma_prior(rng):
    """pull adds -(pull / N) log sigma to F (the stream's weak prior, kernels/estep.py), with its gradient."""
    e = mixture(rng)
    a = 1.5 * np.abs(e).max()
    for sigma, d in [(0.3, 2.0), (8.0, 1.0), (300.0, 0.5)]:
        F0, gs0, gd0 = estep_objective(math.log(sigma), math.log(d), e, e.size, a, 0.0)
        F, gs, gd = estep_objective(math.log(sigma), math.log(d), e, e.size, a, 0.7)
        assert F == pytest.approx(F0 - 0.7 * math.log(sigma) / e.size, rel=1e-13)
        assert gs == pytest.approx(gs0 - 0.7 / e.size, rel=1e-13)
        assert gd == gd0


def test_sigma_pull_resolves_the_gaussian_ridge(rng):
    """Gaussian residuals: the likelihood is flat in sigma beyond the residuals' range, so where ML
    stops depends on the start; with the pull every start ends at sigma_hi."""
    e = rng.normal(0.0, 1.0, 256)
    a = 1.5 * np.abs(e).max()
    ends = []
    for s0 in (6.0, 30.0, 400.0):
        s, d, F, its, st = estep_channel(e, e.size, a, s0, 1.0, LO, HI, 1e-6 * a, a, 100, 1e-7, 0.05, np.zeros(3))
        ends.append(s)
        assert d == pytest.approx(np.std(e), rel=0.05)
    assert ends == pytest.approx([HI] * 3, rel=1e-12)
    # the pull is weak: a real optimum (20% of gross errors) stays where ML puts it
    e2 = mixture(rng, N=256)
    a2 = 1.5 * np.abs(e2).max()
    s_ml = estep_channel(e2, e2.size, a2, 20.0, 1.0, LO, HI, 1e-6 * a2, a2, 200, 1e-10, 0.0, np.zeros(3))[0]
    s_pull = estep_channel(e2, e2.size, a2, 20.0, 1.0, LO, HI, 1e-6 * a2, a2, 200, 1e-10, 0.05, np.zeros(3))[0]
    assert s_ml < 10 and s_pull == pytest.approx(s_ml, rel=0.05)
