"""The attitude's roll/pitch error in the vector fit: corrected least squares (vector_fit.py module doc)."""
import numpy as np
import pytest

from mkc_stream._validation import MKCInputError
from mkc_stream.flight.simulated import _euler_to_quat
from mkc_stream.flight.vector_fit import VectorFitSettings, body_field, fit_vector, rotation_matrices, tilt_error_covariance


def _tilted_run(seed, tilt_error_deg=2.0, n=20000):
    """Banked and pitched attitudes (10 and 5 deg sd) while turning; the log's roll and pitch carry a white error."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 10.0
    yaw = np.cumsum(np.full(n, 0.01))
    pitch, roll = rng.normal(0, np.radians(5), n), rng.normal(0, np.radians(10), n)
    h = np.array([20.0, 0.0, 45.0])
    A, b = np.diag([1.02, 0.99, 0.97]), np.array([5.0, -3.0, 10.0])
    m = body_field(rotation_matrices(_euler_to_quat(yaw, pitch, roll)), h) @ A.T + b + rng.normal(0, 0.1, (n, 3))
    e = np.radians(tilt_error_deg)
    q_log = _euler_to_quat(yaw, pitch + rng.normal(0, e, n), roll + rng.normal(0, e, n))
    return t, m, q_log, h, A, b


def test_tilt_error_covariance_is_that_of_delta_cross_h():
    rng = np.random.default_rng(3)
    h = np.array([[12.0, -5.0, 40.0]])
    d = np.zeros((200000, 3))
    d[:, :2] = rng.normal(0, 0.01, (200000, 2))
    u = np.cross(d, h[0])
    assert np.allclose(tilt_error_covariance(h, 1e-4)[0], u.T @ u / u.shape[0], atol=2e-4)


def test_corrected_least_squares_removes_the_vertical_gain_shrinkage():
    """A 2 deg roll/pitch error in the log shrinks A_22 by ~6% (b_z off by ~2.7 uT along the ridge); with the error's
    sd given, A_22 and b_z come back."""
    t, m, q, h, A, b = _tilted_run(0)
    plain = fit_vector(t, m, q, h, None, (), VectorFitSettings(robust=False, yaw_knot_s=None))
    fixed = fit_vector(t, m, q, h, None, (), VectorFitSettings(robust=False, yaw_knot_s=None, tilt_sd_deg=2.0))
    assert plain.A[2, 2] - A[2, 2] < -0.04 and abs(plain.b[2] - b[2]) > 1.5
    assert abs(fixed.A[2, 2] - A[2, 2]) < 0.01 and abs(fixed.b[2] - b[2]) < 0.4
    # under the kernel weights the correction is approximate (module doc): it must still remove most of the shift
    robust_plain = fit_vector(t, m, q, h, None, (), VectorFitSettings(yaw_knot_s=None))
    robust = fit_vector(t, m, q, h, None, (), VectorFitSettings(yaw_knot_s=None, tilt_sd_deg=2.0))
    assert abs(robust.b[2] - b[2]) < 0.3 * abs(robust_plain.b[2] - b[2])


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_tilt_sd_must_be_a_non_negative_angle(bad):
    t, m, q, h, *_ = _tilted_run(1, n=500)
    with pytest.raises(MKCInputError, match="tilt_sd_deg"):
        fit_vector(t, m, q, h, None, (), VectorFitSettings(tilt_sd_deg=bad))
