"""The attitude's roll/pitch error, estimated from the flight's own residuals (vector_fit.py corrects for it).

The regressor of the vector fit is h_k = R_log,k^T h_E. A tilt error delta_k (a rotation about the
body's x and y axes) changes it by u_k = delta_k x h_k, a vector perpendicular to h_k. The residual
e_k = m_k - A h_k - ... then carries -A u_k. Of the directions perpendicular to h_k one,
    g_k = R_log,k^T (e_z x h_E)       (horizontal in NED),
is what a yaw error produces too (yaw_error.py fits it); the other,
    n_k = (h_k x g_k) / |h_k x g_k|   (in the vertical plane through the horizontal field),
only a tilt error produces. The tilt about the axis along g_k moves the field along n_k by
delta_perp |h_E|, so the residual's component
    r_k = n_k . A^-1 e_k = -delta_perp,k |h_E| + n_k . A^-1 (noise_k)
holds the tilt error at full field strength, with no yaw error in it. An AHRS's tilt error wanders
over seconds, while the sensor noise is white from one sample to the next, so the autocovariance at
a lag of a few samples holds only the first:
    E[r_k r_(k+L)] = |h_E|^2 s^2 rho(L dt),   s^2 = var(delta_perp), rho ~ 1 for L dt << its correlation time,
and the estimate is s = sqrt(c_L) / |h_E| with c_L the weighted mean of r_k r_(k+L), each pair
weighted by the product of the two samples' smallest kernel weights (disturbed samples count
little). Measured on simulated flights with 0.1, 0.3 and 1.0 deg of tilt error (5 s correlation
time, 10 Hz): 0.12, 0.25-0.31 and 0.76-0.90 deg (tests/test_flight_tilt_error.py). A tilt error
that were white would be missed (then it is indistinguishable from sensor noise, and small).
Other slow errors along n_k (an unmodelled vertical disturbance) read as tilt error: the estimate
is an upper bound, and the correction it drives is checked to leave the normal matrix positive
definite (vector_fit.fit_vector).
"""
from __future__ import annotations

import math

import numpy as np

#: The lag (samples) of the autocovariance: the smallest, where rho is nearest 1.
LAG = 1


def tilt_direction(R, h_ned) -> np.ndarray:
    """n_k (N, 3) of the module doc: the unit body-frame direction only a tilt error moves the field along."""
    from .vector_fit import body_field

    h_ned = np.asarray(h_ned, dtype=np.float64)
    h = body_field(R, h_ned)
    g = body_field(R, np.cross([0.0, 0.0, 1.0], h_ned))
    n = np.cross(h, g)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def estimate_tilt_sd_deg(R, h_ned, A, residuals, weights, lag=LAG) -> float:
    """s (deg) of the module doc from the fitted A (3, 3), the residuals (N, 3) and kernel weights (N, 3)
    (ones for least squares); 0 when the lagged covariance is not positive (no slow tilt error seen)."""
    F = float(np.linalg.norm(h_ned))
    n = tilt_direction(R, h_ned)
    r = np.einsum("ki,ki->k", np.asarray(residuals) @ np.linalg.inv(A).T, n)
    w = np.min(weights, axis=1)
    if r.shape[0] <= lag + 1 or not F > 0:
        return 0.0
    ww = w[:-lag] * w[lag:]
    if not np.sum(ww) > 0:
        return 0.0
    c = float(np.sum(ww * r[:-lag] * r[lag:]) / np.sum(ww))
    return math.degrees(math.sqrt(c) / F) if c > 0 else 0.0
