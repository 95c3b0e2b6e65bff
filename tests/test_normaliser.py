"""The truncated MKC pdf's normaliser (eq. (17)) against 40-digit references and its derivatives."""
import math

import mpmath
import numpy as np
import pytest

from mkc_stream.kernels.normaliser import log_normaliser, log_normaliser_grad
from mkc_stream.pdf import mkc_logpdf, mkc_pdf


def load_reference(data_dir):
    return np.genfromtxt(data_dir / "mkc_normaliser.csv", delimiter=",", comments="#", skip_header=4)


def mp_logZ(sigma, A):
    mpmath.mp.dps = 30
    s = mpmath.mpf(sigma)
    f = lambda u: mpmath.exp(-s**2 * (1 - mpmath.exp(-u**2 / (2 * s**2))))  # noqa: E731
    # split at multiples of sigma and of 1 so the quadrature sees the head
    pts = sorted({0.0, *[min(A, k * sigma) for k in (0.5, 1, 2, 4, 8, 16)], *[min(A, k) for k in (1, 2, 4, 8, 16, 32)], A})
    return float(mpmath.log(2 * mpmath.quad(f, pts)))


def test_reference_grid_relative_error(data_dir):
    ref = load_reference(data_dir)
    assert ref.shape[0] >= 180
    rel = [abs(math.expm1(log_normaliser(s, A) - lz)) for s, A, lz in ref]
    assert max(rel) <= 1e-12, max(rel)      # issue asks 1e-8; we hold 1e-12 over the whole grid


@pytest.mark.parametrize("seed", range(3))
def test_random_points_against_mpmath(seed):
    rng = np.random.default_rng(seed)
    for _ in range(6):
        sigma = float(np.exp(rng.uniform(np.log(0.05), np.log(1000))))
        A = float(np.exp(rng.uniform(np.log(0.3), np.log(2e4))))
        assert abs(math.expm1(log_normaliser(sigma, A) - mp_logZ(sigma, A))) <= 1e-10, (sigma, A)


@pytest.mark.parametrize("sigma,A", [(0.07, 3.0), (0.5, 40.0), (2.0, 10.0), (3.3, 500.0), (6.5, 60.0), (40.0, 7.0), (900.0, 3.0)])
def test_gradients_match_finite_differences(sigma, A):
    lz, ds, dA = log_normaliser_grad(sigma, A)
    hs, hA = 1e-6 * sigma, 1e-6 * A
    fs = (log_normaliser(sigma + hs, A) - log_normaliser(sigma - hs, A)) / (2 * hs)
    fA = (log_normaliser(sigma, A + hA) - log_normaliser(sigma, A - hA)) / (2 * hA)
    # central differences carry ~1e-16 / h of rounding noise
    assert ds == pytest.approx(fs, rel=1e-5, abs=1e-9 + 1e-15 / hs)
    assert dA == pytest.approx(fA, rel=1e-5, abs=1e-15 / hA)
    # dZ/dA = 2 f(A) exactly
    assert dA == pytest.approx(2 * math.exp(-sigma**2 * -math.expm1(-A * A / (2 * sigma**2)) - lz), rel=1e-13)


def test_large_a_over_d_never_underflows():
    # The known trap: naive quadrature of [-A, A] misses the head and returns Z = 0.
    for sigma in (1.0, 5.0, 30.0):
        v = log_normaliser(sigma, 1e6)
        assert math.isfinite(v)
        # Z = 2 A exp(-sigma^2) + (head), so log Z >= log(2 A) - sigma^2
        assert v >= math.log(2e6) - sigma**2 - 1e-12


def test_gaussian_limit_corollary_1():
    # sigma -> inf: Z -> sqrt(2 pi) erf(A / sqrt 2)  (Corollary 1)
    for A in (1.0, 3.0, 50.0):
        assert math.exp(log_normaliser(1000.0, A)) == pytest.approx(math.sqrt(2 * math.pi) * math.erf(A / math.sqrt(2)), rel=1e-5)


def test_pdf_integrates_to_one():
    from scipy.integrate import quad

    for sigma, d, a in [(0.3, 1.0, 5.0), (2.0, 0.5, 20.0), (10.0, 2.0, 8.0)]:
        total = quad(lambda e: mkc_pdf(e, sigma, d, a), -a, a, points=[0.0, -d, d], limit=200)[0]
        assert total == pytest.approx(1.0, rel=1e-8)
    assert mkc_pdf(30.0, 2.0, 1.0, 20.0) == 0.0
    with pytest.raises(ValueError):
        mkc_logpdf(1.0, 2.0, 1.0)          # finite sigma needs a finite a
