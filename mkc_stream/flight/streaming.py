"""The attitude-aided calibration in fixed memory: sample by sample, on the streaming MKC-EM.

The vector model of vector_fit.py (units: m in the sensor's unit, h in uT, c in A or 0..1),
    m_k = A h_k + b + K c_k + e_k,     h_k = R(q_k)^T h_E,
is linear per output axis i in theta_i = (A_i0, A_i1, A_i2, b_i, K_i.) with the regressor
x_k = (h_k, 1, c_k). Stacked over the three axes it is the paper's multi-output regression
(Li et al., eq. (13)),
    y_k = X_k theta + e_k,   y_k = m_k,   X_k = blockdiag(x_k^T, x_k^T, x_k^T) T,   theta = T q,
with three residual channels, each with its own kernel (sigma_i, d_i). T holds what a flight cannot
observe (vector_fit.constraint_matrix): "tilt" (the default for a flight: A02 = A20, A12 = A21),
"all" (also A22 = (A00 + A11) / 2: a ground robot, yaw only) or None (a hand rotation). StreamingMKC
runs exactly this: a window of W samples, the reweighted normal equations updated per sample
(Algorithm 1), the warm-started per-channel E-step every K samples (Algorithm 2); its state is the
fixed-size table the C port mirrors. Memory: W (3 n_q + 3) reals plus the n_q x n_q factors.

The window is organised by the direction of the Earth field in the body frame, h_k / |h_k| (the
72 cells and the slot rule of kernels/magwindow.py): what determines A and b is how many directions
the window holds, not how recent its samples are, and a flight's window of the last W samples may
hold one straight leg. Measured on simulated 10-minute flights at 25 Hz: FIFO windows of 512 / 2048
samples left the hard iron 1.1-4.4 / 0.6-1.6 uT off.

What the batch fit (calibrate.fit_flight) does and this does not: the search over the power
signal's delay (feed the signal already delayed, or pass the batch fit's delay to `delay_samples`),
the attitude's wandering yaw error (a nuisance term over the whole flight), the observability test
(the hold is chosen here, not measured) and the cold-start confirmation of the ellipsoid stream.
"""
from __future__ import annotations

import numpy as np

from .._validation import MKCInputError
from ..defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from ..kernels import magwindow as MW
from ..stream import StreamingMKC
from .calibrate import package_form
from .vector_fit import body_field, constraint_matrix, rotation_matrices

HOLDS = (None, "tilt", "all")
POLICIES = ("direction", "fifo")


class FlightStreamCalibrator:
    """Streaming attitude-aided calibration against a known Earth field h_ned (uT, NED).

    power_names: the power signals fed with each sample (e.g. ("current",)); hold_vertical: None,
    "tilt" or "all" (module doc); delay_samples: the power signal is used this many samples late
    (a ring of delay_samples + 1 rows, fixed memory)."""

    def __init__(self, h_ned, power_names=(), hold_vertical="tilt", window=DEFAULT_WINDOW,
                 estep_every=DEFAULT_ESTEP_EVERY, delay_samples=0, policy="direction", **stream_kw):
        h = np.asarray(h_ned, dtype=np.float64).reshape(-1)
        if h.shape != (3,) or not np.isfinite(h).all() or not np.linalg.norm(h) > 0:
            raise MKCInputError(f"h_ned must be 3 finite numbers (uT, NED), not all 0; got {h_ned!r}")
        if hold_vertical not in HOLDS:
            raise MKCInputError(f"hold_vertical must be one of {HOLDS}; got {hold_vertical!r}")
        if policy not in POLICIES:
            raise MKCInputError(f"policy must be one of {POLICIES}; got {policy!r}")
        if isinstance(delay_samples, bool) or not isinstance(delay_samples, (int, np.integer)) or delay_samples < 0:
            raise MKCInputError(f"delay_samples must be an integer >= 0; got {delay_samples!r}")
        self.h_ned = h
        self.power_names = tuple(power_names)
        self.n_c = len(self.power_names)
        self.T, self.held = constraint_matrix(self.n_c, hold_vertical, [False] * self.n_c)
        self.stream = StreamingMKC(self.T.shape[1], 3, window=window, estep_every=estep_every, **stream_kw)
        self.delay_samples = int(delay_samples)
        self._ring = np.zeros((self.delay_samples + 1, self.n_c))
        self._ring_n = 0
        self.policy = policy
        W = self.stream.config.window
        self.slot_cell = np.zeros(W, dtype=np.int64)
        self.slot_age = np.zeros(W, dtype=np.int64)
        self.cell_count = np.zeros(MW.N_CELLS, dtype=np.int64)
        self._age = 0

    # -- feeding ---------------------------------------------------------------------------
    def _delayed(self, c):
        """c_k delay_samples samples late (the first ones use the oldest row held)."""
        if self.delay_samples == 0 or self.n_c == 0:
            return c
        out = np.empty_like(c)
        D = self.delay_samples + 1
        for k in range(c.shape[0]):
            self._ring[self._ring_n % D] = c[k]
            self._ring_n += 1
            oldest = max(0, self._ring_n - D)
            out[k] = self._ring[oldest % D]
        return out

    def regressors(self, q, c) -> np.ndarray:
        """X_k (T, 3, n_q) of attitudes q (T, 4) (w, x, y, z; body -> NED) and power rows c (T, n_c)."""
        h = body_field(rotation_matrices(q), self.h_ned)
        x = np.concatenate([h, np.ones((h.shape[0], 1)), c], axis=1)            # (T, n_x)
        nx = x.shape[1]
        T3 = self.T.reshape(3, nx, -1)                                           # theta_i = T3[i] q
        return np.einsum("kj,ijq->kiq", x, T3)

    def learn_many(self, mag, q, power=None) -> np.ndarray:
        """Feed samples: mag (T, 3), q (T, 4), power (T, n_c) or None when there is no power signal.
        Rows with a non-finite value or a quaternion far from unit norm are rejected and counted
        (StreamingMKC.samples_rejected). Returns the kernel status per sample (-1: rejected here)."""
        mag = np.atleast_2d(np.asarray(mag, dtype=np.float64))
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        c = np.zeros((mag.shape[0], 0)) if power is None else np.atleast_2d(np.asarray(power, dtype=np.float64))
        if power is not None and c.shape[0] != mag.shape[0] and c.size == mag.shape[0] * self.n_c:
            c = c.reshape(mag.shape[0], self.n_c)
        if mag.shape[1:] != (3,) or q.shape != (mag.shape[0], 4) or c.shape != (mag.shape[0], self.n_c):
            raise MKCInputError(f"expected mag (T, 3), q (T, 4) and power (T, {self.n_c}); got {mag.shape}, "
                                f"{q.shape}, {c.shape}")
        qn = np.linalg.norm(q, axis=1)
        bad = ~(np.isfinite(q).all(axis=1) & (np.abs(qn - 1.0) < 0.1) & np.isfinite(c).all(axis=1)
                & np.isfinite(mag).all(axis=1))
        q = np.where(bad[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q)
        c = self._delayed(np.where(bad[:, None], 0.0, c))
        X = np.ascontiguousarray(self.regressors(q, c))
        Y = np.ascontiguousarray(np.where(bad[:, None], np.nan, mag))  # a NaN row is rejected and counted
        if self.policy == "fifo":
            return self.stream.learn_many(X, Y)
        status = np.full(X.shape[0], -1, dtype=np.int8)
        self.stream.count_rejected(int(bad.sum()))
        hb = body_field(rotation_matrices(q), self.h_ned)
        W = self.stream.config.window
        for k in np.flatnonzero(~bad):
            u = hb[k] / np.linalg.norm(hb[k])
            cell = MW.direction_cell(u[0], u[1], u[2])
            count = self.stream.window_count
            slot = MW.choose_slot(cell, count, W, self.slot_cell, self.slot_age, self.cell_count)
            if count == W:
                self.cell_count[self.slot_cell[slot]] -= 1
            self.slot_cell[slot] = cell
            self.slot_age[slot] = self._age
            self.cell_count[cell] += 1
            self._age += 1
            status[k] = self.stream.learn_one(X[k], Y[k], slot)
        return status

    # -- results ---------------------------------------------------------------------------
    def parameters(self):
        """(A (3, 3), b (3,), K (3, n_c)) of the current estimate."""
        theta = (self.T @ self.stream.theta).reshape(3, 4 + self.n_c)
        return theta[:, :3].copy(), theta[:, 3].copy(), theta[:, 4:].copy()

    def calibration(self) -> dict:
        """The current estimate in the package's form: hard_iron b, soft_iron S (det 1), field F (sensor
        unit), scale (sensor unit per uT), misalignment_deg (rotation vector), current / power
        coefficients K (sensor unit per power unit), held parameters, channels' (sigma, d)."""
        A, b, K = self.parameters()
        S, field, scale, mis = package_form(A, float(np.linalg.norm(self.h_ned)))
        return {"hard_iron": b, "soft_iron": S, "field": field, "scale": scale, "misalignment_deg": mis,
                "power": {n: K[:, j] for j, n in enumerate(self.power_names)}, "held": list(self.held),
                "channels": [{"sigma": float(s), "d": float(d)} for s, d in zip(self.stream.sigma, self.stream.d)],
                "samples_seen": self.stream.samples_seen, "esteps": self.stream.esteps}

    def nbytes(self) -> int:
        return self.stream.nbytes() + self._ring.nbytes + self.T.nbytes
