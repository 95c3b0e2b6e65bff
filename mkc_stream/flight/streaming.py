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
fixed-size table the C port mirrors. Memory: the stream's state, W x 3 reals for the yaw term and the
n_q x n_q pool (nbytes(): 228520 bytes at W = 512 with one power signal).

The window is organised by the direction of the Earth field in the body frame, h_k / |h_k| (the
72 cells and the slot rule of kernels/magwindow.py): what determines A and b is how many directions
the window holds, not how recent its samples are, and a flight's window of the last W samples may
hold one straight leg.

Trial, pool, accepted: the same verbs and results as calib.streaming.MagCalibrator (learn_one /
learn_many / accepted / trial / status / history / apply; a Calibration, or a Rejection saying why
not). At every E-step checkpoint the window's estimate is a *trial*, judged by the checks of _gates
(fitted gain against the field model, outlier fraction, residual, condition). A trial that passes
lets the samples that entered the window since the last checkpoint join the *pool*, each once, with
the kernel weights c_ki = w_ki / d_i^2 the window's E-step gave them (at a (re)start: the whole
window):
    H <- lam H + sum_new X_k^T C_k X_k,   g <- lam g + sum_new X_k^T C_k y_k,   theta_pool = H^-1 g,
lam = 1 - 1 / N per checkpoint, N = POOL_WINDOWS W / K (an exponential memory of about POOL_WINDOWS
window turnovers). The pool is the reweighted least squares of eq. (16) over the whole flight (fixed
memory: n_q x n_q), with each sample judged by the kernel of its own window. One window of a level
flight pins the vertical terms (A_22 against b_z) only as well as its pitch excitation allows: window
to window its hard iron moves by several tenths of a uT. A trial farther from the pool than
RESTART_FACTOR x max_disagreement_rel x field (in b) W / K times in a row restarts the pool from it
(the calibration changed); a pool younger than W / K members restarts at the first such trial. The
*accepted* calibration is the pool's, with the uncertainty of the window it was last updated on (a
sandwich covariance, _uncertainty).

The attitude's yaw error: a nuisance dpsi_j per segment of the pool's samples (10 s by default),
eliminated when its segment closes (_add_yaw), the piecewise-constant form of vector_fit.py's term.
The batch fit pins the mean of its yaw error to 0; here the segments' priors already do: the data fix
each dpsi_j + (A's rotation about z), and the priors pull every dpsi_j to 0, which puts their mean
into A (a pin of the sum at 1e4 times the prior, tried, left the test flight's result unchanged to 10
digits).

Measured (simulated_flight, 10 minutes at 25 Hz, seeds 1-6, W = 512, 3 deg RMS of yaw error;
hard-iron error median (max), uT, at 0 / 10 / 25% disturbed): the window's trial 0.82 (1.79) / 1.05
(1.67) / 1.17 (5.09); the pool without the yaw term 0.45 (1.58) / 0.45 (2.00) / 0.51 (1.89), with it
0.18 (0.31) / 0.27 (0.68) / 0.40 (0.66). docs/flight.md has the other figures and what was tried.

What the batch fit (calibrate.fit_flight) does and this does not: the search over the power
signal's delay (feed the signal already delayed, or pass the batch fit's delay to `delay_samples`),
the observability test (the hold is chosen here, not measured), the unit field with an estimated
inclination (a field reference is needed) and the mean of the yaw error pinned to 0 (here each
segment's prior pulls it there). The ellipsoid stream's cold-start confirmation has no counterpart.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Optional

import numpy as np

from .._validation import MKCInputError
from ..calib.acceptance import AcceptanceRules
from ..calib.result import Calibration, Rejection
from ..calib.streaming import CheckpointEvent, NotCalibratedError
from ..defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from ..jsonout import jsonable
from ..kernels import magwindow as MW
from ..kernels import window as KW
from ..stream import StreamingMKC
from .calibrate import package_form
from .vector_fit import body_field, constraint_matrix, rotation_matrices
from .yaw_error import KNOT_S, PRIOR_SD_DEG

HOLDS = (None, "tilt", "all")
POLICIES = ("direction", "fifo")
#: a trial's fitted gain (sensor uT per model uT) must lie within this fraction of 1 for a stream in uT
FIELD_TOLERANCE = 0.15
#: a window sample is an inlier when its smallest kernel weight w = exp(-e^2 / (2 d^2 sigma^2)) is above this
INLIER_WEIGHT = 0.5
#: a trial farther than this many times the rules' max_disagreement_rel x field from the pool disagrees with
#: it: one window's hard iron scatters by up to about 1 uT around the truth in level flight (measured,
#: 10-minute simulated flights at 25 Hz, W = 512), which is 2% of a 50 uT field
RESTART_FACTOR = 3.0


@dataclass(frozen=True)
class FlightStreamCalibration(Calibration):
    """A Calibration of the attitude-aided stream: m_cal = S (m_raw - b - K c), det S = 1.

    Beside the Calibration's fields: the power coefficients K per signal (sensor unit per signal
    unit), their 95% intervals (the window's sandwich covariance), the delay used, the Earth field
    reference, the fitted gain (sensor unit per uT), the misalignment rotation vector (deg) and the
    parameters held."""

    power: dict = dc_field(default_factory=dict)
    power_ci: dict = dc_field(default_factory=dict)
    delay_s: Optional[float] = None
    earth: object = None
    h_ned: Optional[np.ndarray] = None
    scale: float = math.nan
    misalignment_deg: Optional[np.ndarray] = None
    held: tuple = ()
    unit: str = "uT"
    pooled: int = 0

    @property
    def current(self):
        return self.power.get("current")

    @property
    def throttle(self):
        return self.power.get("throttle")

    def apply(self, raw, power=None):
        """S (m - b - K c) for raw samples (T, 3) and power rows (T, n_c) in power's order (None: no
        compensation)."""
        m = np.atleast_2d(np.asarray(raw, dtype=np.float64)) - self.hard_iron
        if power is not None and self.power:
            K = np.stack([self.power[n] for n in self.power], axis=1)
            m = m - np.atleast_2d(np.asarray(power, dtype=np.float64)).reshape(m.shape[0], -1) @ K.T
        return m @ self.soft_iron.T

    def to_json(self, counts=None) -> dict:
        """The `calibrate` object with `compensation` and `earth_field` (docs/spec/machine-output.md)."""
        out = super().to_json(counts)
        lst = (lambda x: None if x is None else [float(v) for v in np.ravel(x)])
        comp = None
        if self.power:
            ci = self.power_ci.get("current")
            comp = {"current": lst(self.current), "current_unit": f"{self.unit}/A", "throttle": lst(self.throttle),
                    "delay_s": self.delay_s,
                    "current_ci": None if ci is None else [[float(a), float(b)] for a, b in ci]}
        earth = None
        if self.earth is not None and hasattr(self.earth, "to_json"):
            earth = self.earth.to_json()
        out.update({"compensation": comp, "earth_field": earth,
                    "attitude_fit": {"scale_per_uT": jsonable(self.scale), "misalignment_deg": lst(self.misalignment_deg),
                                     "held": list(self.held), "h_ned_uT": lst(self.h_ned),
                                     "trials_pooled": int(self.pooled)}})
        return out


class FlightStreamCalibrator:
    """Streaming attitude-aided calibration against a known Earth field h_ned (uT, NED).

    power_names: the power signals fed with each sample (e.g. ("current",)); hold_vertical: None,
    "tilt" or "all" (module doc); delay_samples: the power signal is used this many samples late
    (a ring of delay_samples + 1 rows, fixed memory); policy: "direction" (default) or "fifo";
    unit: the magnetometer's unit ("uT" enables the check of the fitted gain against the model);
    yaw_prior_deg: prior sd (deg) of the attitude's yaw error, a nuisance per segment of yaw_segment
    samples (_add_yaw; None: not modelled);
    rules: the AcceptanceRules whose outlier, residual, condition and disagreement limits apply;
    earth: the EarthField h_ned came from (reported only); sample_rate: Hz, to report the delay in s."""

    #: the pool's memory, in window turnovers (module doc), as MagCalibrator's
    POOL_WINDOWS = 32

    def __init__(self, h_ned, power_names=(), hold_vertical="tilt", window=DEFAULT_WINDOW,
                 estep_every=DEFAULT_ESTEP_EVERY, delay_samples=0, policy="direction", unit="uT",
                 rules=AcceptanceRules(), earth=None, sample_rate=None, keep_history=True, yaw_prior_deg=PRIOR_SD_DEG,
                 yaw_segment=250, **stream_kw):
        h = np.asarray(h_ned, dtype=np.float64).reshape(-1)
        if h.shape != (3,) or not np.isfinite(h).all() or not np.linalg.norm(h) > 0:
            raise MKCInputError(f"h_ned must be 3 finite numbers (uT, NED), not all 0; got {h_ned!r}")
        if hold_vertical not in HOLDS:
            raise MKCInputError(f"hold_vertical must be one of {HOLDS}; got {hold_vertical!r}")
        if policy not in POLICIES:
            raise MKCInputError(f"policy must be one of {POLICIES}; got {policy!r}")
        if isinstance(delay_samples, bool) or not isinstance(delay_samples, (int, np.integer)) or delay_samples < 0:
            raise MKCInputError(f"delay_samples must be an integer >= 0; got {delay_samples!r}")
        if not isinstance(rules, AcceptanceRules):
            raise MKCInputError(f"rules must be an AcceptanceRules; got {type(rules).__name__}")
        self.h_ned = h
        self.power_names = tuple(power_names)
        self.n_c = len(self.power_names)
        self.T, self.held = constraint_matrix(self.n_c, hold_vertical, [False] * self.n_c)
        self.stream = StreamingMKC(self.T.shape[1], 3, window=window, estep_every=estep_every, **stream_kw)
        if self.stream.config.estep_every > self.stream.config.window:
            raise MKCInputError(f"estep_every {estep_every} must be <= window {window}: trials are judged at E-steps")
        self.delay_samples = int(delay_samples)
        self.policy = policy
        self.unit = unit
        self.rules = rules
        self.earth = earth
        self.sample_rate = sample_rate
        self.keep_history = keep_history
        if yaw_prior_deg is not None and not (math.isfinite(yaw_prior_deg) and yaw_prior_deg > 0):
            raise MKCInputError(f"yaw_prior_deg must be > 0 (deg) or None; got {yaw_prior_deg!r}")
        if isinstance(yaw_segment, bool) or not isinstance(yaw_segment, (int, np.integer)) or yaw_segment < 1:
            raise MKCInputError(f"yaw_segment must be an integer >= 1 (samples); got {yaw_segment!r}")
        self.yaw_precision = None if yaw_prior_deg is None else 1.0 / math.radians(yaw_prior_deg) ** 2
        self.yaw_segment = int(yaw_segment)
        self.reset()

    def reset(self):
        W = self.stream.config.window
        n = self.T.shape[1]
        self.stream.reset()
        self._ring = np.zeros((self.delay_samples + 1, self.n_c))
        self._ring_n = 0
        self.slot_cell = np.zeros(W, dtype=np.int64)
        self.slot_age = np.zeros(W, dtype=np.int64)
        self.cell_count = np.zeros(MW.N_CELLS, dtype=np.int64)
        self._age = 0
        self.pool_H = np.zeros((n, n))
        self.pool_g = np.zeros(n)
        self.pool_theta = np.zeros(n)
        self.pool_n = 0
        self.pool_streak = 0
        self._pool_mark = 0
        self.slot_yaw = np.zeros((W, 3))                  # R_k^T (e_z x h_E) of each window sample
        self._open = {}                                   # yaw segment -> [h_td (n_q,), h_dd, g_d]
        self.trial = None
        self.accepted = None
        self.last_rejection = None
        self.last_event = None
        self.first_accepted_at = None
        self.history = []
        return self

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

    def learn_one(self, mag, q, power=None) -> list:
        """Feed one sample: mag (3,), q (4,), power (n_c,) or None. Returns the checkpoint events (0 or 1)."""
        p = None if power is None else np.reshape(np.asarray(power, dtype=np.float64), (1, -1))
        return self.learn_many(np.reshape(np.asarray(mag, dtype=np.float64), (1, -1)),
                               np.reshape(np.asarray(q, dtype=np.float64), (1, -1)), p)

    def learn_many(self, mag, q, power=None) -> list:
        """Feed samples: mag (T, 3), q (T, 4), power (T, n_c) or None when there is no power signal.
        Rows with a non-finite value or a quaternion far from unit norm are rejected and counted
        (counts()["bad_frames"]). Returns the checkpoint events (CheckpointEvent) they produced."""
        mag = np.atleast_2d(np.asarray(mag, dtype=np.float64))
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        c = np.zeros((mag.shape[0], 0)) if power is None else np.atleast_2d(np.asarray(power, dtype=np.float64))
        if power is not None and c.shape[0] != mag.shape[0] and c.size == mag.shape[0] * self.n_c:
            c = c.reshape(mag.shape[0], self.n_c)
        if mag.shape[1:] != (3,) or q.shape != (mag.shape[0], 4) or c.shape != (mag.shape[0], self.n_c):
            raise MKCInputError(f"expected mag (T, 3), q (T, 4) and power (T, {self.n_c}); got {mag.shape}, "
                                f"{q.shape}, {c.shape}")
        with np.errstate(invalid="ignore", over="ignore"):
            qn = np.linalg.norm(q, axis=1)
            bad = ~(np.isfinite(q).all(axis=1) & (np.abs(qn - 1.0) < 0.1) & np.isfinite(c).all(axis=1)
                    & np.isfinite(mag).all(axis=1))
        q = np.where(bad[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q)
        c = self._delayed(np.where(bad[:, None], 0.0, c))
        X = np.ascontiguousarray(self.regressors(q, c))
        self.stream.count_rejected(int(bad.sum()))
        Rq = rotation_matrices(q)
        hb = body_field(Rq, self.h_ned)
        gy = body_field(Rq, np.array([-self.h_ned[1], self.h_ned[0], 0.0]))        # R^T (e_z x h_E)
        W = self.stream.config.window
        events = []
        for k in np.flatnonzero(~bad):
            cell = MW.direction_cell(hb[k, 0], hb[k, 1], hb[k, 2])
            count = self.stream.window_count
            if self.policy == "direction":
                slot = MW.choose_slot(cell, count, W, self.slot_cell, self.slot_age, self.cell_count)
            else:                               # the oldest sample's slot: a ring buffer
                slot = count if count < W else int(self._age % W)
            if count == W:
                self.cell_count[self.slot_cell[slot]] -= 1
            self.slot_cell[slot] = cell
            self.slot_age[slot] = self._age
            self.slot_yaw[slot] = gy[k]
            self.cell_count[cell] += 1
            self._age += 1
            esteps = self.stream.esteps
            self.stream.learn_one(X[k], mag[k], slot)
            if self.stream.esteps > esteps:
                self.last_event = ev = self._checkpoint()
                events.append(ev)
        return events

    # -- checkpoints -----------------------------------------------------------------------
    def _window(self):
        """(X (n, 3, n_q), Y (n, 3), C (n, 3), A (n_q, n_q) symmetric) of the window's samples."""
        count = self.stream.window_count
        A = np.tril(self.stream.view("A"))
        return (self.stream.view("X")[:count], self.stream.view("Y")[:count], self.stream.view("C")[:count],
                A + np.tril(A, -1).T)

    def _calibration(self, theta, accepted, rejection, quality, uncertainty=None, power_sd=None, pooled=0):
        """The FlightStreamCalibration of theta; power_sd (3, n_c): the coefficients' sd for their 95% intervals."""
        th = (self.T @ theta).reshape(3, 4 + self.n_c)
        A, b, K = th[:, :3], th[:, 3].copy(), th[:, 4:]
        S, field, scale, mis = package_form(A, float(np.linalg.norm(self.h_ned)))
        seen, esteps = self.stream.samples_seen, self.stream.esteps
        ci = {} if power_sd is None else {n: np.stack([K[:, j] - 1.96 * power_sd[:, j], K[:, j] + 1.96 * power_sd[:, j]],
                                                      axis=1) for j, n in enumerate(self.power_names)}
        delay = None
        if self.n_c:
            delay = self.delay_samples / self.sample_rate if self.sample_rate else (0.0 if self.delay_samples == 0 else None)
        return FlightStreamCalibration(
            b, S, field, quality, accepted, rejection, method="mkc-em-attitude-stream",
            channels=[{"sigma": float(s), "d": float(d)} for s, d in zip(self.stream.sigma, self.stream.d)],
            uncertainty=uncertainty, samples_seen=seen, esteps=esteps,
            power={n: K[:, j].copy() for j, n in enumerate(self.power_names)}, power_ci=ci, delay_s=delay,
            earth=self.earth, h_ned=self.h_ned.copy(), scale=scale, misalignment_deg=mis, held=tuple(self.held),
            unit=self.unit, pooled=pooled)

    def _judge(self, X, Y, C):
        """(quality figures, the window's residuals e (n, 3)) of the stream's current theta: residual_rms over
        the inliers (sensor unit), coverage (the 72 cells of the body-frame field direction), outlier
        fraction, condition of the equilibrated normal matrix."""
        theta = self.stream.theta
        d = self.stream.d
        e = Y - np.einsum("kiq,q->ki", X, theta)
        w = C * d[None, :] ** 2                        # the kernel weights exp(-e^2 / (2 d^2 sigma^2))
        inl = w.min(axis=1) >= INLIER_WEIGHT
        n = max(1, e.shape[0])
        rms = float(np.sqrt(np.mean(np.sum(e[inl] ** 2, axis=1)))) if inl.any() else math.nan
        cond = float(self.stream.snapshot().condition)
        quality = {"residual_rms": rms, "coverage": float((self.cell_count > 0).sum()) / MW.N_CELLS,
                   "outlier_fraction": 1.0 - float(inl.sum()) / n, "condition": cond}
        return quality, e

    def _checkpoint(self) -> CheckpointEvent:
        seen, esteps = self.stream.samples_seen, self.stream.esteps
        W = self.stream.config.window
        count = self.stream.window_count
        rejection = None
        cal = None
        if self.stream.status_code not in (KW.OK, KW.NOT_CONVERGED):
            rejection = Rejection("no_calibration", f"the window's normal equations are {self.stream.status}")
        elif count < W:
            rejection = Rejection("warming_up", f"warming up: {count}/{W} samples in the window",
                                  values={"samples": count, "needed": W})
        if rejection is None:
            X, Y, C, A = self._window()
            quality, e = self._judge(X, Y, C)
            try:
                cal = self._calibration(self.stream.theta, False, None, quality)
            except MKCInputError as exc:                # package_form: a mirrored field
                rejection = Rejection("rejected", str(exc), ("mirror",))
            else:
                rejection = self._gates(cal, quality)
                cal = replace(cal, accepted=rejection is None, rejection=rejection)
                self.trial = cal
                if rejection is None:
                    self._offer(cal, X, e, C, A, quality)
        self.last_rejection = rejection
        ev = CheckpointEvent(seen, esteps, rejection is None, "" if rejection is None else rejection.text,
                             None if cal is None else cal.hard_iron, None if cal is None else cal.field,
                             None if cal is None else cal.quality["coverage"],
                             None if cal is None else cal.quality["outlier_fraction"])
        if self.keep_history:
            self.history.append(ev)
        return ev

    def _gates(self, cal, quality):
        """The Rejection of a trial that fails a check, None when it passes."""
        r = self.rules
        failed, values, why = [], {}, []
        if self.unit == "uT" and not abs(cal.scale - 1.0) <= FIELD_TOLERANCE:
            failed.append("field_model")
            values["scale"] = cal.scale
            why.append(f"fitted field {cal.scale:.3f} x the Earth-field model (more than {FIELD_TOLERANCE:.0%} from 1)")
        if not quality["outlier_fraction"] <= r.max_outlier_fraction:
            failed.append("outliers")
            values["outlier_fraction"] = quality["outlier_fraction"]
            why.append(f"{quality['outlier_fraction']:.0%} of the window treated as disturbed "
                       f"(> {r.max_outlier_fraction:.0%})")
        rel = quality["residual_rms"] / cal.field if cal.field > 0 else math.inf
        if not rel <= r.max_residual_rel:
            failed.append("residual")
            values["residual_rel"] = rel
            why.append(f"residual {rel:.1%} of the field (> {r.max_residual_rel:.0%})")
        if not quality["condition"] <= r.max_condition:
            failed.append("condition")
            values["condition"] = quality["condition"]
            why.append(f"condition {quality['condition']:.3g} (> {r.max_condition:.3g}): the window does not "
                       "determine the model")
        if not failed:
            return None
        return Rejection("rejected", "trial rejected: " + "; ".join(why), tuple(failed), values)

    def _offer(self, cal, X, e, C, A, quality):
        """A passing trial joins the pool, or restarts it (module doc); the pool becomes the accepted one."""
        per_window = max(1, self.stream.config.window // self.stream.config.estep_every)
        if self.pool_n > 0:
            pool_b = (self.T @ self.pool_theta).reshape(3, -1)[:, 3]
            far = np.linalg.norm(cal.hard_iron - pool_b) > RESTART_FACTOR * self.rules.max_disagreement_rel * abs(cal.field)
            self.pool_streak = self.pool_streak + 1 if far else 0
            if far and self.pool_n >= per_window and self.pool_streak < per_window:
                return                                   # one disagreeing trial of a settled pool: not a member
            if far:
                self.pool_n = 0                          # a young pool, or the data moved on: restart here
        self.pool_streak = 0
        lam = 1.0 - 1.0 / (self.POOL_WINDOWS * per_window) if self.pool_n else 0.0
        if not self.pool_n:
            self._open = {}
        # the samples that entered the window since the last checkpoint (at a (re)start: the whole window)
        count = X.shape[0]
        new = self.slot_age[:count] >= (self._pool_mark if self.pool_n else -1)
        Xn, Cn, Yn = X[new], C[new], self.stream.view("Y")[:count][new]
        self.pool_H = lam * self.pool_H + np.einsum("kiq,ki,kir->qr", Xn, Cn, Xn)
        self.pool_g = lam * self.pool_g + np.einsum("kiq,ki,ki->q", Xn, Cn, Yn)
        self._pool_mark = self._age
        if self.yaw_precision is not None:
            self._add_yaw(lam, Xn, Cn, Yn, self.slot_yaw[:count][new], self.slot_age[:count][new])
        self.pool_n += 1
        try:
            self.pool_theta = np.linalg.solve(*self._pool_system())
        except np.linalg.LinAlgError:
            self.pool_theta = self.stream.theta.copy()
        unc, power_sd = self._uncertainty(X, e, C, A, cal)
        try:
            acc = self._calibration(self.pool_theta, True, None, quality, unc, power_sd, self.pool_n)
        except MKCInputError:
            return
        self.accepted = acc
        if self.first_accepted_at is None:
            self.first_accepted_at = cal.samples_seen

    def _add_yaw(self, lam, Xn, Cn, Yn, g0, ages):
        """The yaw-error nuisance of the pool: one dpsi_j per segment of yaw_segment samples, prior N(0,
        yaw_prior^2), in the model y_k = X_k theta + dpsi_j z_k, z_k = A R_k^T (e_z x h_E) (A the pool's, the
        linearisation point; vector_fit.py's term, piecewise constant here). Each segment's bordered
        terms (h_td = sum X^T C z, h_dd = sum z^T C z + prior, g_d = sum z^T C y) are kept while samples
        of it can still join, then eliminated (Schur complement), so the memory stays n_q + 2 per open
        segment: H <- H - h_td h_td^T / h_dd,  g <- g - h_td g_d / h_dd."""
        A = (self.T @ (self.pool_theta if self.pool_n else self.stream.theta)).reshape(3, -1)[:, :3]
        z = g0 @ A.T
        seg = ages // self.yaw_segment
        for o in self._open.values():
            o[0] *= lam
            o[1] *= lam
            o[2] *= lam
        for j in np.unique(seg):
            m = seg == j
            Cz = Cn[m] * z[m]
            o = self._open.setdefault(int(j), [np.zeros(self.pool_g.shape), self.yaw_precision, 0.0])
            o[0] += np.einsum("kiq,ki->q", Xn[m], Cz)
            o[1] += float(np.sum(Cz * z[m]))
            o[2] += float(np.sum(Cz * Yn[m]))
        done = [j for j in self._open if (j + 1) * self.yaw_segment <= self._pool_mark]
        for j in done:
            htd, hdd, gd = self._open.pop(j)
            self.pool_H -= np.outer(htd, htd) / hdd
            self.pool_g -= htd * gd / hdd

    def _pool_system(self):
        """(H, g) of the pool with the open yaw segments eliminated (they stay open in the pool)."""
        H, g = self.pool_H.copy(), self.pool_g.copy()
        for htd, hdd, gd in self._open.values():
            H -= np.outer(htd, htd) / hdd
            g -= htd * gd / hdd
        return H, g

    def _uncertainty(self, X, e, C, A, cal):
        """The window's sandwich covariance of theta (samples independent, so a lower bound):
            Cov(theta_q) = H^-1 (sum_k g_k g_k^T) H^-1,   g_k = X_k^T (c_k * e_k),   H = sum_k X_k^T C_k X_k,
        mapped by T; returns ({"hard_iron_sd", "heading_sd_deg"}, the power coefficients' sd (3, n_c)).
        The heading sd is what the horizontal hard-iron sd does to a level heading in the Earth
        field's horizontal component (sensor unit: times the fitted gain)."""
        try:
            Hi = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            return None, None
        G = np.einsum("kiq,ki->kq", X, C * e)
        cov = self.T @ (Hi @ (G.T @ G) @ Hi) @ self.T.T
        nx = 4 + self.n_c
        var = np.diag(cov).reshape(3, nx)
        if not (np.isfinite(var).all() and (var >= 0).all()):
            return None, None
        sd = np.sqrt(var)
        horiz = float(np.linalg.norm(self.h_ned[:2])) * (cal.scale if math.isfinite(cal.scale) else 1.0)
        unc = {"hard_iron_sd": [float(v) for v in sd[:, 3]],
               "heading_sd_deg": math.degrees(math.sqrt(0.5 * (var[0, 3] + var[1, 3])) / horiz) if horiz > 0 else None}
        return unc, sd[:, 4:]

    # -- results ---------------------------------------------------------------------------
    def parameters(self, pooled=True):
        """(A (3, 3), b (3,), K (3, n_c)) of the pool (pooled and a trial has been accepted) or of the window."""
        theta = self.pool_theta if pooled and self.pool_n else self.stream.theta
        th = (self.T @ theta).reshape(3, 4 + self.n_c)
        return th[:, :3].copy(), th[:, 3].copy(), th[:, 4:].copy()

    def calibration(self, pooled=True) -> dict:
        """The current estimate in the package's form: hard_iron b, soft_iron S (det 1), field F (sensor
        unit), scale (sensor unit per uT), misalignment_deg (rotation vector), current / power
        coefficients K (sensor unit per power unit), held parameters, channels' (sigma, d)."""
        A, b, K = self.parameters(pooled)
        S, field, scale, mis = package_form(A, float(np.linalg.norm(self.h_ned)))
        return {"hard_iron": b, "soft_iron": S, "field": field, "scale": scale, "misalignment_deg": mis,
                "power": {n: K[:, j] for j, n in enumerate(self.power_names)}, "held": list(self.held),
                "channels": [{"sigma": float(s), "d": float(d)} for s, d in zip(self.stream.sigma, self.stream.d)],
                "samples_seen": self.stream.samples_seen, "esteps": self.stream.esteps}

    def apply(self, mag, power=None):
        """Calibrate raw samples with the ACCEPTED calibration only (FlightStreamCalibration.apply)."""
        if self.accepted is None:
            raise NotCalibratedError(f"no calibration accepted yet ({self.status_reason()})")
        return self.accepted.apply(mag, power)

    def status(self) -> Rejection | None:
        """None when a calibration is accepted and the last trial passed, else why not (yet)."""
        W, count = self.stream.config.window, self.stream.window_count
        if self.stream.esteps == 0 or count < W and self.last_rejection is None:
            return Rejection("warming_up", f"warming up: {count}/{W} samples in the window",
                             values={"samples": count, "needed": W})
        return self.last_rejection

    def status_reason(self) -> str:
        r = self.status()
        return "accepted" if r is None else r.text

    def counts(self):
        seen, rejected = self.stream.samples_seen, self.stream.samples_rejected
        return {"samples": seen + rejected, "bad_frames": rejected, "drops": 0, "gaps": 0}

    def nbytes(self) -> int:
        return (self.stream.nbytes() + self._ring.nbytes + self.T.nbytes + self.slot_cell.nbytes + self.slot_age.nbytes
                + self.cell_count.nbytes + self.pool_H.nbytes + self.pool_g.nbytes + self.pool_theta.nbytes
                + self.slot_yaw.nbytes)


def recording_inputs(rec, *, earth=None, lat=None, lon=None, alt=0.0, date=None, yaw_only=False,
                     window=DEFAULT_WINDOW, estep_every=DEFAULT_ESTEP_EVERY):
    """(FlightStreamCalibrator, mag (T, 3), q (T, 4), power (T, n_c) or None, notes) to replay a Recording.

    The recording needs the attitude (aux qw, qx, qy, qz: body -> NED) and a field reference: earth
    (an earthfield.EarthField or an NED vector in uT), or a position (lat/lon/alt in deg, deg, m, or
    the recording's median GPS position) for WMM2025 at `date` (as fit_flight). The power signal is
    the current when the recording has it, else the throttle; it is used without delay (the stream
    does not search one). yaw_only holds the vertical soft iron ("all"), else the tilt terms ("tilt").
    MKCInputError, with the reason, when the attitude or the field reference is missing."""
    from .calibrate import QUAT, earth_reference, require_attitude

    require_attitude(rec, "stream")
    notes = []
    ef, h = earth_reference(rec, earth, lat, lon, alt, date, notes)
    if h is None:
        raise MKCInputError("the attitude-aided stream needs the Earth field: a position in the recording "
                            "(lat, lon) or --lat/--lon (the batch fit, without --stream, can estimate the "
                            "inclination instead)")
    names = ()
    for n in ("current", "throttle"):
        if n in rec.aux:
            finite = float(np.mean(np.isfinite(rec.aux[n])))
            if finite >= 0.5:
                names = (n,)
                notes.append(f"power signal: {n}, used without delay (the stream does not search one)")
                break
            notes.append(f"{n} left out: finite in only {finite:.0%} of the rows (its rows would all be rejected)")
    dt = np.diff(rec.t[np.isfinite(rec.t)])
    dt = dt[dt > 0]
    rate = 1.0 / float(np.median(dt)) if dt.size else None
    cal = FlightStreamCalibrator(h, names, hold_vertical="all" if yaw_only else "tilt", window=window,
                                 estep_every=estep_every, unit=rec.mag_unit, earth=ef, sample_rate=rate,
                                 yaw_segment=max(1, int(round(KNOT_S * rate))) if rate else 250)
    q = np.stack([rec.aux[c] for c in QUAT], axis=1)
    power = np.stack([rec.aux[n] for n in names], axis=1) if names else None
    return cal, rec.mag, q, power, notes
