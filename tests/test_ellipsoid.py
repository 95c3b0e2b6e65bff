"""Ellipsoid model (appendix eqs. (36)-(40)), conversion to (b, S, F), degenerate geometry."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mkc_stream import EllipsoidError, MKCInputError, fit_ellipsoid
from mkc_stream.calib.ellipsoid import design_matrix, geometry_from_theta, quadric_from_theta
from mkc_stream.calib.synthetic import random_soft_iron, synthetic_mag


def clean_samples(rng, S, b, F, N=600):
    u = rng.normal(size=(N, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return (F * u) @ np.linalg.inv(S).T + b


@pytest.mark.parametrize("method", ["mkc-em", "ls", "mkc"])
def test_exact_recovery_without_noise(rng, method):
    S = random_soft_iron(rng, 0.4)
    b = np.array([12.0, -40.0, 7.5])
    raw = clean_samples(rng, S, b, 48.0)
    fit = fit_ellipsoid(raw, method)
    np.testing.assert_allclose(fit.hard_iron, b, atol=1e-8)
    np.testing.assert_allclose(fit.soft_iron, S, atol=1e-9)       # entry by entry: no mirror, no rotation
    assert fit.field == pytest.approx(48.0, rel=1e-10)
    np.testing.assert_allclose(np.linalg.norm(fit.apply(raw), axis=1), 48.0, rtol=1e-9)


def test_soft_iron_is_symmetric_pd_and_not_mirrored_for_any_axis_order(rng):
    # axes along +-x/y/z in every permutation and sign: the eigen-decomposition's freedom must not leak into S
    for perm in ([0, 1, 2], [2, 0, 1], [1, 2, 0]):
        for signs in ([1, 1, 1], [-1, 1, 1], [1, -1, -1]):
            Q = np.eye(3)[:, perm] * signs
            S = Q @ np.diag([1.3, 1.0, 1 / 1.3]) @ Q.T
            raw = clean_samples(rng, S, np.zeros(3) + 5.0, 30.0, 300)
            fit = fit_ellipsoid(raw, "ls")
            np.testing.assert_allclose(fit.soft_iron, fit.soft_iron.T, atol=0)
            assert np.all(np.linalg.eigvalsh(fit.soft_iron) > 0)
            np.testing.assert_allclose(fit.soft_iron, S, atol=1e-9)
            assert np.linalg.det(fit.soft_iron) == pytest.approx(1.0, rel=1e-12)


def test_units_scale_exactly(rng):
    S = random_soft_iron(rng)
    raw = clean_samples(rng, S, np.array([6000.0, 250.0, 3500.0]) / 100, 0.5)
    f1 = fit_ellipsoid(raw, "ls")
    f2 = fit_ellipsoid(raw * 1e4, "ls")          # gauss -> counts
    np.testing.assert_allclose(f2.hard_iron, f1.hard_iron * 1e4, rtol=1e-9)
    np.testing.assert_allclose(f2.soft_iron, f1.soft_iron, atol=1e-9)
    assert f2.field == pytest.approx(1e4 * f1.field, rel=1e-10)


def test_paper_geometry_equations(rng):
    # a known quadric: (m - c)^T M (m - c) = 1 rewritten in the form of eq. (36)
    c = np.array([1.0, -2.0, 0.5])
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    axes = np.array([2.0, 3.0, 5.0])
    M = R @ np.diag(1 / axes**2) @ R.T
    k = 1 - c @ M @ c                 # m^T M m - 2 c^T M m = 1 - c^T M c
    A, B = M / k, -2 * M @ c / k
    theta = np.array([A[0, 0], A[1, 1], A[2, 2], 2 * A[0, 1], 2 * A[0, 2], 2 * A[1, 2], *B])
    A2, B2 = quadric_from_theta(theta)
    np.testing.assert_allclose(A2, A)
    g = geometry_from_theta(theta)
    np.testing.assert_allclose(g.centre, c, atol=1e-12)                  # eq. (38)
    np.testing.assert_allclose(np.sort(g.semi_axes), np.sort(axes), rtol=1e-12)   # eq. (39)
    assert np.linalg.det(g.rotation) == pytest.approx(1.0)
    pts = g.surface(8, 16).reshape(-1, 3)                                # eq. (40)-(41)
    np.testing.assert_allclose(design_matrix(pts) @ theta, 1.0, atol=1e-10)


def test_too_few_points(rng):
    with pytest.raises(EllipsoidError, match="too few"):
        fit_ellipsoid(rng.normal(size=(8, 3)))


def test_planar_data_rotation_about_one_axis():
    ang = np.linspace(0, 2 * np.pi, 500)
    raw = np.stack([30 * np.cos(ang) + 5, 30 * np.sin(ang) - 3, np.full_like(ang, 20.0)], 1)
    with pytest.raises(EllipsoidError, match="plane"):
        fit_ellipsoid(raw)


def test_hyperboloid_is_not_an_ellipsoid(rng):
    # points on x^2 + y^2 - z^2 = 1
    t = rng.uniform(-1.5, 1.5, 800)
    ang = rng.uniform(0, 2 * np.pi, 800)
    r = np.sqrt(1 + t**2)
    raw = np.stack([r * np.cos(ang), r * np.sin(ang), t], 1) * 40
    with pytest.raises(EllipsoidError, match="not an ellipsoid"):
        fit_ellipsoid(raw, "ls")


def test_nan_and_bad_shape():
    with pytest.raises(MKCInputError, match="NaN"):
        fit_ellipsoid(np.array([[1.0, 2.0, np.nan]] * 20))
    with pytest.raises(MKCInputError, match="shape"):
        fit_ellipsoid(np.zeros((20, 2)))
    with pytest.raises(MKCInputError, match="unknown method"):
        fit_ellipsoid(np.random.default_rng(0).normal(size=(50, 3)), "nope")


def test_robust_to_bursts_where_least_squares_is_not():
    s = synthetic_mag(seed=3, burst_fraction=0.1)
    em = fit_ellipsoid(s.raw, "mkc-em")
    ls = fit_ellipsoid(s.raw, "ls")
    assert np.linalg.norm(em.hard_iron - s.hard_iron) < 0.1 < 0.5 < np.linalg.norm(ls.hard_iron - s.hard_iron)
    assert np.abs(em.soft_iron - s.soft_iron).max() < 0.005
    assert em.field == pytest.approx(50.0, rel=2e-3)
    # the weights mark the bursts: disturbed samples are down-weighted
    assert np.median(em.weights[s.disturbed]) < 0.1 < 0.9 < np.median(em.weights[~s.disturbed])
    q = em.quality
    assert q["coverage"] > 0.9 and 0.05 < q["outlier_fraction"] < 0.15 and q["condition"] < 1e3
    j = em.to_json(counts={"samples": 2000, "bad_frames": 0, "drops": 0, "gaps": 0})
    assert set(j) >= {"hard_iron", "soft_iron", "field", "channels", "quality", "status", "reason", "counts"}
    assert j["channels"][0]["sigma"] > 0


# ---- gross isolated spikes (glitched or saturated reads): the high-breakdown start ----------------

@pytest.mark.parametrize("fraction, magnitude", [(0.03, 5000.0), (0.15, 300.0), (0.3, 1000.0)])
def test_gross_spikes_do_not_move_the_calibration(fraction, magnitude):
    """From the WLS start (the paper's) 15% of spikes at 300 uT gave a 600 uT "field"; from the
    trimmed sphere with a narrow first kernel, and d free down to 1e-9 a, the spikes get weight 0."""
    for seed in range(3):
        s = synthetic_mag(seed=seed, burst_fraction=0.1, spike_fraction=fraction, spike_magnitude=magnitude)
        mkc = fit_ellipsoid(s.raw, method="mkc-em")
        ls = fit_ellipsoid(s.raw, method="ls")
        assert np.linalg.norm(mkc.hard_iron - s.hard_iron) < 0.1
        assert abs(mkc.field - s.field) < 0.1
        assert np.linalg.norm(ls.hard_iron - s.hard_iron) > 5.0     # the spikes are not harmless


def test_robust_sphere_fit_trims_gross_spikes_before_its_first_fit():
    from mkc_stream.calib.ellipsoid import robust_sphere_fit

    s = synthetic_mag(seed=4, N=256, burst_fraction=0.0, spike_fraction=0.15, spike_magnitude=1000.0)
    b, F = robust_sphere_fit(s.raw)
    # a sphere through an ellipsoid with 25% soft iron: a few uT, where the plain first fit was ~300 uT off
    assert np.linalg.norm(b - s.hard_iron) < 5.0
    assert abs(F - s.field) < 5.0


def test_sphere_theta_is_the_sphere():
    from mkc_stream.calib.ellipsoid import calibration_from_geometry, sphere_theta

    theta = sphere_theta((0.2, -0.1, 0.3), 1.4)
    b, S, F = calibration_from_geometry(geometry_from_theta(theta))
    assert np.allclose(b, [0.2, -0.1, 0.3]) and np.isclose(F, 1.4) and np.allclose(S, np.eye(3))
    assert sphere_theta((2.0, 0.0, 0.0), 1.0) is None        # the origin outside: no "= 1" form
