"""The attitude's slowly wandering yaw error as a nuisance of the vector fit (vector_fit.py).

An AHRS's yaw is its weakest angle: errors of 2-5 deg that wander over tens of seconds. While the
vehicle turns slowly, such an error correlates with the heading and leaks into the hard iron (measured
on simulated flights: 1 deg RMS of yaw error with a 30 s correlation time moved b by up to 0.5 uT,
3 deg by up to 1.4 uT). The logged attitude is R_log = Rz(dpsi) R_true (a rotation about the
vertical in NED), so the true body field is, to first order in dpsi,
    R_true^T h_E = R_log^T Rz(dpsi) h_E ~ R_log^T (h_E + dpsi e_z x h_E),
and the model gains a term dpsi(t_k) g_k with g_k = A R_log,k^T (e_z x h_E). dpsi(t) is piecewise
linear on knots every knot_s seconds: dpsi(t_k) = sum_j beta_j phi_j(t_k) (hat functions), with the
Gaussian prior beta_j ~ N(0, prior_sd^2) (rad) and its mean pinned to 0 (a constant yaw offset is
the misalignment about z that A already holds). g_k uses A from the previous iterate
(alternating least squares: the term is small and A changes little between iterations).
"""
from __future__ import annotations

import math

import numpy as np

#: Knot spacing of the yaw-error spline, s: shorter than the error's correlation time (tens of s)
#: and long enough that every knot interval holds a heading change while the vehicle turns.
KNOT_S = 10.0
#: Prior standard deviation of the yaw error at a knot, deg (the AHRS's stated 2-5 deg).
PRIOR_SD_DEG = 5.0


class YawBasis:
    """Hat functions on knots every knot_s seconds over t."""

    #: The mean of beta is pinned to 0 by a penalty MEAN_WEIGHT times the prior's on (sum beta)^2: the
    #: data cannot tell a constant yaw error from A's rotation about z, and with the prior alone the
    #: alternating iteration drifted along that flat valley (measured: 11 deg on a level run).
    MEAN_WEIGHT = 1e4

    def __init__(self, t, knot_s=KNOT_S, prior_sd_deg=PRIOR_SD_DEG):
        t = np.asarray(t, dtype=np.float64)
        self.knot_s = float(knot_s)
        self.n = max(2, int(math.ceil((t[-1] - t[0]) / self.knot_s)) + 1)
        pos = (t - t[0]) / self.knot_s
        self.j = np.minimum(np.floor(pos).astype(np.int64), self.n - 2)
        self.u = pos - self.j
        self.prior_precision = 1.0 / math.radians(prior_sd_deg) ** 2

    def eval(self, beta) -> np.ndarray:
        """dpsi(t_k), rad."""
        return beta[self.j] * (1.0 - self.u) + beta[self.j + 1] * self.u

    def gram(self, v) -> np.ndarray:
        """Phi^T diag(v) Phi (n, n), tridiagonal."""
        a, c = 1.0 - self.u, self.u
        G = np.zeros((self.n, self.n))
        d0 = np.bincount(self.j, v * a * a, self.n) + np.bincount(self.j + 1, v * c * c, self.n)
        off = np.bincount(self.j, v * a * c, self.n)[: self.n - 1]
        G[np.arange(self.n), np.arange(self.n)] = d0
        G[np.arange(self.n - 1), np.arange(1, self.n)] = off
        G[np.arange(1, self.n), np.arange(self.n - 1)] = off
        return G

    def project(self, v) -> np.ndarray:
        """Phi^T v (n,)."""
        return np.bincount(self.j, v * (1.0 - self.u), self.n) + np.bincount(self.j + 1, v * self.u, self.n)

    def cross(self, X, a) -> np.ndarray:
        """X^T diag(a) Phi (n_x, n)."""
        out = np.empty((X.shape[1], self.n))
        for col in range(X.shape[1]):
            out[col] = self.project(a * X[:, col])
        return out

    def scores(self, v) -> np.ndarray:
        """Phi scaled by v in sparse form (a dense (N, n) matrix would be large): (j (N,), rows (N, 2)), sample k
        touching knots j_k and j_k + 1."""
        return self.j, np.stack([v * (1.0 - self.u), v * self.u], axis=1)


def yaw_regressor(R, h_ned, A) -> np.ndarray:
    """g_k = A R_k^T (e_z x h_E), (N, 3): the change of the model per radian of yaw error."""
    h = np.asarray(h_ned, dtype=np.float64)
    ezh = np.array([-h[1], h[0], 0.0])
    return np.einsum("kji,j->ki", R, ezh) @ np.asarray(A).T
