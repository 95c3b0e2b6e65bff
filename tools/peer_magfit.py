"""Peer for tools/study_flight.py: ArduPilot's MagFit (MAVProxy, MAVExplorer's `magfit`), reimplemented
from its published description and source (read, not copied).

MAVProxy's module imports wxPython when it is imported (its GUI) and reads its samples from a
DataFlash log through pymavlink; PyPI has no Linux wheel of wxPython, so it cannot run headless here
and this file implements the same cost and bounds on arrays.

MagFit's correction of a raw sample m_k (ArduPilot's parameter convention: offsets are added):
    c_k = M s (m_k + o) + cmot I_k
M symmetric with diagonal (COMPASS_DIA) and off-diagonal (COMPASS_ODI) terms, s the scale
(COMPASS_SCALE), o the offsets (COMPASS_OFS), cmot the motor-current compensation per ampere
(COMPASS_MOT, current-based), I_k the battery current of the latest battery sample (no delay).
Its reference is the Earth field rotated into the body by the log's roll and pitch and by a yaw taken
from the corrected sample itself (its tilt-compensated heading plus the declination). The yaw drops
out: with n_k = R_k c_k (R_k the log's attitude, body -> NED; any yaw gives the same norms), the
error it sums is, in closed form,
    f_k = sqrt((|n_k,h| - H)^2 + (n_k,z - Z)^2),  n_k,h = (n_k,x, n_k,y),
H = the model's horizontal intensity, Z its down component: MagFit's expected field and the corrected
one share their heading, so only the horizontal magnitude and the vertical component differ. It
minimises mean_k f_k (a mean of vector norms, not of squares) by SLSQP with box bounds:
offsets within +-OffsetMax (1500 mGauss = 150 uT), s in [ScaleMin, ScaleMax] (1, 1: held), diagonal
in [0.8, 1.2], off-diagonal in [-0.2, 0.2], cmot within +-CMOT Max (10 mGauss/A = 1 uT/A): the
defaults of its command line. Its start is the log's current parameters; a log without an onboard
calibration gives zero offsets, M = I, cmot = 0, which is the start here unless one is given.

Conversion to the study's model m = A h + b + K I: A = (s M)^-1, b = -o, K = -(s M)^-1 cmot, no delay.
This module's gradient is analytic (MagFit's SLSQP uses finite differences; the minimum is the same).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: MagFit's default bounds, in uT (its own unit is mGauss = 0.1 uT).
OFFSET_MAX_UT = 150.0
DIAGONAL = (0.8, 1.2)
OFF_DIAGONAL = (-0.2, 0.2)
SCALE = (1.0, 1.0)
CMOT_MAX_UT_PER_A = 1.0
#: Smoothing of |.| at 0 (uT): keeps the gradient finite where a residual is exactly zero (noiseless data).
EPS_UT = 1e-9


@dataclass
class MagFitResult:
    offsets: np.ndarray      # o (3,), uT, added to the raw sample
    scale: float             # s
    M: np.ndarray            # (3, 3) symmetric
    cmot: np.ndarray         # (3,), uT per A, added after M
    cost: float              # mean_k f_k at the optimum, uT
    success: bool
    message: str

    def vector_model(self):
        """(A, b, K) of m = A h + b + K I (module doc)."""
        A = np.linalg.inv(self.scale * self.M)
        return A, -self.offsets, -A @ self.cmot


def _unpack(p):
    o = p[0:3]
    s = p[3]
    dg, od = p[4:7], p[7:10]
    M = np.array([[dg[0], od[0], od[1]], [od[0], dg[1], od[2]], [od[1], od[2], dg[2]]])
    return o, s, M, p[10:13]


def _cost_and_gradient(p, mag, R, current, H, Z):
    """mean_k f_k (module doc) and its gradient in p = (o, s, diag, offdiag, cmot)."""
    o, s, M, cmot = _unpack(p)
    u = mag + o                                   # (N, 3)
    Mu = u @ M.T
    c = s * Mu + current[:, None] * cmot[None, :]
    n = np.einsum("kij,kj->ki", R, c)
    nh = np.hypot(n[:, 0], n[:, 1])
    rh, rz = nh - H, n[:, 2] - Z
    f = np.sqrt(rh * rh + rz * rz + EPS_UT * EPS_UT)
    N = mag.shape[0]
    # df/dn, then df/dc = R^T df/dn
    dn = np.stack([rh * n[:, 0] / np.maximum(nh, 1e-300), rh * n[:, 1] / np.maximum(nh, 1e-300), rz], axis=1) / f[:, None]
    g = np.einsum("kji,kj->ki", R, dn)            # (N, 3)
    grad = np.empty(13)
    grad[0:3] = s * (g.sum(axis=0) @ M)           # dc/do = s M
    grad[3] = np.sum(g * Mu)                      # dc/ds = M u
    G = s * (g.T @ u)                             # dF/dM_ij = s sum g_i u_j
    grad[4:7] = np.diag(G)
    grad[7] = G[0, 1] + G[1, 0]
    grad[8] = G[0, 2] + G[2, 0]
    grad[9] = G[1, 2] + G[2, 1]
    grad[10:13] = g.T @ current
    return float(f.sum() / N), grad / N


def magfit(mag, R, h_ned, current=None, start=None, ftol=1e-10, max_iter=500) -> MagFitResult:
    """MagFit's fit (module doc). mag (N, 3) uT; R (N, 3, 3) the log's attitude, body -> NED; h_ned (3,)
    the model field in uT; current (N,) A or None (then cmot is held at 0); start: (o, s, M, cmot) or None."""
    from scipy.optimize import minimize

    mag = np.asarray(mag, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    h = np.asarray(h_ned, dtype=np.float64)
    H, Z = float(np.hypot(h[0], h[1])), float(h[2])
    cur = np.zeros(mag.shape[0]) if current is None else np.asarray(current, dtype=np.float64)
    if start is None:
        p0 = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    else:
        o, s, M, cm = start
        p0 = np.concatenate([o, [s], np.diag(M), [M[0, 1], M[0, 2], M[1, 2]], cm])
    cmax = CMOT_MAX_UT_PER_A if current is not None else 0.0
    bounds = ([(-OFFSET_MAX_UT, OFFSET_MAX_UT)] * 3 + [SCALE] + [DIAGONAL] * 3 + [OFF_DIAGONAL] * 3
              + [(-cmax, cmax)] * 3)
    p0 = np.clip(p0, [b[0] for b in bounds], [b[1] for b in bounds])
    res = minimize(_cost_and_gradient, p0, args=(mag, R, cur, H, Z), jac=True, method="SLSQP", bounds=bounds,
                   options={"ftol": ftol, "maxiter": max_iter})
    o, s, M, cm = _unpack(res.x)
    return MagFitResult(offsets=o.copy(), scale=float(s), M=M, cmot=cm.copy(), cost=float(res.fun),
                        success=bool(res.success), message=str(res.message))
