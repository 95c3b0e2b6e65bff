"""MagCalibrator: the ellipsoid model fed sample by sample through the streaming MKC-EM.

Keeps a *trial* calibration (the latest E-step checkpoint) and an *accepted* one: the running mean
of the trials that passed the acceptance predicate and agree with it (a fit over more than one
window; a pool that restarts when fresh data keep preferring another calibration, _offer_pooled);
apply() uses only the accepted one. Features are the
ellipsoid's 9 terms of (m - c0)/s0; (c0, s0) follow the trial centre and radius, and when they
move the window's features are recomputed from the raw samples kept in the state.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from dataclasses import field as dc_field

import numpy as np

from .._validation import MKCInputError
from ..kernels import magwindow as MW
from ..kernels import window as K
from ..defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from ..stream import StreamingMKC
from .acceptance import AcceptanceRules, coverage_wait_reason, degenerate_reason, evaluate, motion_wait_reason
from .confidence import DOMINANCE, Z_RESTART, calibration_uncertainty, residual_ratio, supports_switch
from .ellipsoid import (EllipsoidError, Normalisation, calibration_from_geometry, geometry_from_theta,
                        raw_geometry, robust_sphere_fit, sphere_theta)
from .fit import weighted_condition
from .quality import quality_figures, sphere_coverage, sphere_spread
from .result import Calibration, Rejection

#: theta of the unit sphere (eq. (36)-(37)): the restart's start once the features are centred and
#: scaled by the window's sphere fit
UNIT_SPHERE_THETA = sphere_theta((0.0, 0.0, 0.0), 1.0)

POLICIES = {"fifo": 0, "direction": 1}
#: "pooled": the accepted calibration is the mean of the passing trials that agree with it (a fit
#: over more than one window), restarted when the data keep preferring a new one (_offer);
#: "paired": a passing trial replaces the accepted calibration only when the window supports it as the
#: better fit (confidence.py); "latest": every passing trial does (the last two for comparison studies)
SWITCHING = ("pooled", "paired", "latest")


def det_one(Sm, F):
    """The mean of trials' (S, F) in the package's convention det S = 1 (m_cal = S (m - b), |m_cal| = F):
    S' = sym(Sm) / c, F' = F / c, c = det(sym(Sm))^(1/3). The mean of det-1 matrices has det 1 only to
    first order (1 + 1e-6 seen). Written out (the 3x3 determinant by its rule, c = exp(log(det) / 3)),
    not through LAPACK, so that the C port computes the same bits."""
    S = 0.5 * (Sm + Sm.T)
    det = (S[0, 0] * (S[1, 1] * S[2, 2] - S[1, 2] * S[2, 1]) - S[0, 1] * (S[1, 0] * S[2, 2] - S[1, 2] * S[2, 0])
           + S[0, 2] * (S[1, 0] * S[2, 1] - S[1, 1] * S[2, 0]))
    c = math.exp(math.log(float(det)) / 3.0)
    return S / c, F / c


class NotCalibratedError(RuntimeError):
    """apply() was called before any calibration was accepted."""


@dataclass
class CheckpointEvent:
    samples_seen: int
    esteps: int
    accepted: bool
    reason: str
    hard_iron: np.ndarray | None = None
    field: float | None = None
    coverage: float | None = None
    outlier_fraction: float | None = None
    extra: dict = dc_field(default_factory=dict)


class MagCalibrator:
    """Live magnetometer calibration on a fixed-size, direction-organised window.

    window W, estep_every K: as StreamingMKC. policy: "direction" (default) or "fifo".
    unit: "uT" enables the physical field-range check. rules: the AcceptanceRules.
    init_samples: samples gathered before the first normalisation (median centre / radius).
    on_checkpoint: fn(calibrator), called after every checkpoint (E-step decision) with the
    calibrator, whose `last_event` is that checkpoint's event (as CMagCalibrator's); more with add_listener.
    """

    #: directions around a sphere fit of the window needed before the final feature normalisation
    MIN_SPHERE_COVERAGE = 0.4
    #: robust spread of |m - c| - r relative to r above which the window's "sphere" is a cloud of
    #: noise around one point (a rest phase: every direction is covered by the noise itself, ~42% for
    #: isotropic noise) rather than a surface (a sphere fit of the strongest soft iron allowed, axes
    #: e^+-0.25, spreads <= ~18%)
    MAX_SPHERE_SPREAD = 0.3
    #: consecutive checkpoints without an ellipsoid before the normalisation is redone
    MAX_FAILED_CHECKPOINTS = 4
    #: consecutive trials that do not fit (fit error or outlier gate) before the estimate restarts
    MAX_MISFIT_TRIALS = 8
    #: E-step + fixed-point rounds of the cold start that confirms a new calibration (batch: 10)
    COLD_START_ROUNDS = 10

    def __init__(self, window=DEFAULT_WINDOW, estep_every=DEFAULT_ESTEP_EVERY, unit="uT", policy="direction", rules=AcceptanceRules(),
                 init_samples=None, keep_history=True, on_checkpoint=None, switching="pooled", **stream_kw):
        if policy not in POLICIES:
            raise MKCInputError(f"policy must be one of {sorted(POLICIES)}")
        if not isinstance(unit, str):
            raise MKCInputError(f"unit must be a string such as 'uT' or 'counts'; got {unit!r}")
        if not isinstance(rules, AcceptanceRules):
            raise MKCInputError(f"rules must be an AcceptanceRules; got {type(rules).__name__}")
        if switching not in SWITCHING:
            raise MKCInputError(f"switching must be one of {SWITCHING}; got {switching!r}")
        self.switching = switching
        self.unit = unit
        self.rules = rules
        self.policy = policy
        self.keep_history = keep_history
        #: called as fn(calibrator) after every checkpoint (its event: `last_event`), in order
        self._listeners = []
        if on_checkpoint is not None:
            self.add_listener(on_checkpoint)
        self.stream = StreamingMKC(9, 1, window=window, estep_every=estep_every, **stream_kw)
        W = self.stream.config.window
        # decisions are taken at E-step checkpoints only: with K > W no checkpoint after the first
        # ever comes, and the calibrator waits forever without saying why
        if self.stream.config.estep_every > W:
            raise MKCInputError(f"estep_every {estep_every} must be <= window {W}: calibrations are checked at E-steps")
        if init_samples is None or (isinstance(init_samples, (int, np.integer)) and init_samples == 0):
            init_samples = min(W, 64)          # (0: the default, as in the C port)
        if isinstance(init_samples, (bool, np.bool_)) or not isinstance(init_samples, (int, np.integer)) \
                or not 1 <= init_samples <= W:
            # more than W would hold an unbounded number of samples before the fixed-size window
            raise MKCInputError(f"init_samples must be an integer in [1, window = {W}]; got {init_samples!r}")
        self.init_samples = int(init_samples)
        self.reset()

    def reset(self):
        W = self.stream.config.window
        self.stream.reset()
        self.raw = np.zeros((W, 3))
        self.slot_cell = np.zeros(W, dtype=np.int64)
        self.slot_age = np.zeros(W, dtype=np.int64)
        self.cell_count = np.zeros(MW.N_CELLS, dtype=np.int64)
        self.c0 = np.zeros(3)
        self.s0 = 0.0
        self.provisional = True
        self._failed = 0
        self._misfit = 0
        self._confirmed = None
        self._xk = np.zeros((1, 9))
        self._yk = np.ones(1)
        self._pending = []
        self.trial: Calibration | None = None
        self.accepted: Calibration | None = None
        self.first_accepted_at: int | None = None
        self.switches = 0
        self.last_switch_test = None
        # the pool (switching="pooled"): the running mean of the agreeing trials' (b, S, F), how many
        # trials it holds (capped at POOL_WINDOWS windows' worth), and how many trials in a row
        # disagreed with it
        self.pool_n = 0
        self.pool_mean = np.zeros(13)
        self.pool_streak = 0
        self.history: list[CheckpointEvent] = []
        self.last_event: CheckpointEvent | None = None
        self.last_rejection: Rejection | None = Rejection("warming_up", "warming up: not enough samples yet")
        return self

    # -- listeners -------------------------------------------------------------------------
    def add_listener(self, fn):
        """Call fn(calibrator) after every checkpoint, after the listeners added before; returns fn."""
        if not callable(fn):
            raise MKCInputError(f"a checkpoint listener must be callable; got {fn!r}")
        self._listeners.append(fn)
        return fn

    def remove_listener(self, fn) -> None:
        self._listeners.remove(fn)

    # -- feeding ---------------------------------------------------------------------------
    def learn_one(self, mag) -> list:
        """Feed one raw sample (3,). Returns the checkpoint events it produced (0 or 1)."""
        return self.learn_many(np.reshape(np.asarray(mag, dtype=np.float64), (1, 3)))

    def learn_many(self, mags) -> list:
        """Feed raw samples (T, 3) or (3,). Returns the checkpoint events they produced."""
        mags = np.ascontiguousarray(np.atleast_2d(np.asarray(mags, dtype=np.float64)))
        if mags.ndim != 2 or mags.shape[1] != 3:
            raise MKCInputError(f"magnetometer samples must have shape (T, 3); got {mags.shape}")
        if self.s0 <= 0:
            # gather init_samples finite samples to set the first normalisation (median centre, radius)
            finite = np.isfinite(mags).all(axis=1)
            self.stream.count_rejected(int((~finite).sum()))
            good = mags[finite]
            need = self.init_samples - len(self._pending)
            self._pending.extend(good[:need])
            if len(self._pending) < self.init_samples:
                return []
            P = np.array(self._pending)
            self.c0 = np.median(P, axis=0)
            self.s0 = float(np.median(np.linalg.norm(P - self.c0, axis=1))) or 1.0
            mags = np.ascontiguousarray(np.concatenate([P, good[need:]]))
            self._pending = []
        events = []
        status = np.empty(mags.shape[0], dtype=np.int8)
        t = 0
        st = self.stream.kernel_state
        args = self.stream.kernel_args
        while t < mags.shape[0]:
            esteps = int(st["cnt"][K.C_ESTEPS])
            t = MW.mag_learn_many(*args, self.raw, self.slot_cell, self.slot_age, self.cell_count, self.c0,
                                  np.float64(self.s0), POLICIES[self.policy], mags, t, status, self._xk, self._yk)
            # after an E-step only: a chunk whose last samples were all rejected right after a
            # checkpoint leaves since == 0 without a new E-step (a duplicate checkpoint otherwise)
            if st["cnt"][K.C_ESTEPS] > esteps and st["cnt"][K.C_STATUS] != K.WARMING_UP and st["cnt"][K.C_SINCE] == 0:
                self.last_event = ev = self._checkpoint()
                events.append(ev)
                for fn in self._listeners:
                    fn(self)
        return events

    #: the former name of learn_many, kept for one release
    update = learn_many

    # -- checkpoints -----------------------------------------------------------------------
    def _window_raw(self):
        count = self.stream.window_count
        return self.raw[:count], count

    def _checkpoint(self) -> CheckpointEvent:
        st = self.stream.kernel_state
        seen, esteps = int(st["cnt"][K.C_SEEN]), int(st["cnt"][K.C_ESTEPS])
        raw, count = self._window_raw()
        if self.provisional:
            # The first normalisation centre came from a few samples, which may all lie on one
            # patch of the ellipsoid's surface: the "= 1" form of eq. (36) degenerates when the
            # features' origin is on the ellipsoid. A sphere fit is well-posed anywhere; once the
            # window's directions around it cover enough of the sphere, re-centre the features
            # there and restart the estimate.
            ev = self._try_final_normalisation(raw, seen, esteps)
            if ev is not None:
                return ev
        sigma, d = float(st["sigma"][0]), float(st["d"][0])
        try:
            geom = raw_geometry(geometry_from_theta(st["theta"]), Normalisation(self.c0.copy(), self.s0))
            b, S, F = calibration_from_geometry(geom)
        except (EllipsoidError, np.linalg.LinAlgError) as exc:
            self.last_rejection = Rejection("not_ellipsoid", f"trial is not an ellipsoid: {exc}")
            ev = CheckpointEvent(seen, esteps, False, self.last_reason)
            if self.keep_history:
                self.history.append(ev)
            self._failed += 1
            if self._failed >= self.MAX_FAILED_CHECKPOINTS:
                # watchdog: a bad normalisation (features centred on the surface) cannot heal
                # itself; go back to the sphere-fit normalisation on the current window
                self.provisional = True
                self._failed = 0
            return ev
        self._failed = 0
        m_cal = (raw - b) @ S.T
        w = st["C"][:count, 0] * d * d
        quality = quality_figures(m_cal, F, weighted_condition(st["X"][:count, 0, :], w))
        rejection = evaluate(quality, F, self.unit, self.rules)
        if rejection is None and self._needs_confirmation(b, F):
            disagreement, cold = self._cold_start_disagreement(raw, b, F)
            rejection = evaluate(quality, F, self.unit, self.rules, disagreement=disagreement)
            if rejection is None:
                self._confirmed = (b, F)
            elif cold is not None:
                b, S, F, quality, sigma, d = cold       # report (and continue from) the cold start
        ok = rejection is None
        # Watchdog: trials that keep failing the fit gates mean the estimate no longer fits the
        # window (e.g. a wrong mode after a disturbance): redo the normalisation and restart.
        misfit = not ok and ("residual" in rejection.failed or "outliers" in rejection.failed)
        self._misfit = self._misfit + 1 if misfit else 0
        if self._misfit >= self.MAX_MISFIT_TRIALS:
            self._misfit = 0
            self.provisional = True
        cal = Calibration(b, S, F, quality, ok, rejection, channels=[{"sigma": sigma, "d": d}],
                          samples_seen=seen, esteps=esteps)
        self.trial = cal
        if ok:
            self._offer(cal, raw)
        self.last_rejection = rejection
        reason = cal.reason
        ev = CheckpointEvent(seen, esteps, ok, reason, b, F, quality["coverage"], quality["outlier_fraction"])
        if self.keep_history:
            self.history.append(ev)
        if ok:                      # only a trustworthy trial may move the feature normalisation
            self._maybe_renormalise(geom, b, F)
        return ev

    #: the pool's memory, in windows: its mean forgets older trials once it holds this many windows'
    #: worth of them (W / K trials per window), so a slow change of the calibration is followed
    POOL_WINDOWS = 32

    def _offer(self, cal, raw):
        """A trial that passed every gate, offered to the accepted calibration.

        "paired"/"latest": it replaces the accepted one when the window supports it as the better fit
        (confidence.supports_switch) / always. "pooled" (_offer_pooled): the accepted calibration is
        the running mean of the trials that agree with it.
        """
        if self.switching == "pooled":
            return self._offer_pooled(cal, raw)
        if self.accepted is not None and self.switching == "paired":
            better, gain, se = supports_switch(raw, cal, self.accepted)
            self.last_switch_test = (gain, se)
            if not better:
                return
        self._accept(cal, raw)

    def _offer_pooled(self, cal, raw):
        """The pooled calibration: the running mean over the trials p_i = (b_i, S_i, F_i) that joined,
            p <- p + (p_i - p) / min(n, N),   N = POOL_WINDOWS * W / K
        (the plain mean of the first N, then an exponential memory of about N trials). A trial joins
        unless it disagrees: the window supports it over the pool (confidence.supports_switch, gain
        > Z_SWITCH se) and it lies farther from the pool than the cold start's tolerance (|b_i - b| or
        |F_i - F| above max_disagreement_rel * F), or the window supports it strongly (gain >
        Z_RESTART se) however close. W / K disagreeing trials in a row (the window has turned over
        and fresh data keep preferring another calibration) restart the pool from the latest. A young pool
        (fewer than W / K trials) follows the paired rule: a trial the window supports replaces it, so
        the first windows of a stream, fitted before the motion covered much, do not weigh on the pool.
        So does a pool that fails the window's fit gates (_pool_fits): it no longer describes the data.
        And so does a pool that a strongly supported trial (gain > Z_RESTART se) fits DOMINANCE times
        better in mean squared residual over the trial's inliers (confidence.residual_ratio): a wrong
        mode the stream locked onto, which can pass the gates to the end of a run (synthetic seeds 3020
        and 3299 at 25% bursts ended 6.5 and 4.0 uT off, their correct trials waiting in line).
        (Under heavy bursts a wrong mode 12 uT off can pass the gates for a while; the window favours the
        correct trials that follow at only ~3 se, so the restart's W / K of them in a row would come
        after the end of a 60 s stream.)

        Why: one window's estimate moves with that window's noise (hard-iron sd 0.05-0.1 uT per axis
        on a real recording), so the result depended on which window a run ended on; overlapping
        windows averaged over the run do not, and a disturbed window that passed the gates is one
        member among many. The window's preference alone cannot be the test: windows of different
        directions prefer their own fit over any average, since a real field is not an exact ellipsoid.
        """
        member = np.concatenate([cal.hard_iron, np.asarray(cal.soft_iron, dtype=np.float64).ravel(), [cal.field]])
        per_window = max(1, self.stream.config.window // self.stream.config.estep_every)
        if self.pool_n > 0:
            better, gain, se = supports_switch(raw, cal, self.accepted)
            self.last_switch_test = (gain, se)
            tol = self.rules.max_disagreement_rel * abs(self.pool_mean[12])
            db = member[:3] - self.pool_mean[:3]
            # written out (not np.linalg.norm) so that the C port computes the same bits
            far = math.sqrt(db[0] * db[0] + db[1] * db[1] + db[2] * db[2]) > tol or \
                abs(member[12] - self.pool_mean[12]) > tol
            strong = gain > Z_RESTART * se
            # a pool the window's strongly supported trial beats by DOMINANCE in mean squared residual
            # is a wrong mode: it gives way at once (waiting W / K trials in a row can outlast the stream)
            dominant = strong and residual_ratio(raw, cal, self.accepted) > DOMINANCE
            # a young pool, or one that no longer fits the window: the paired rule, the better trial replaces it
            if better and (self.pool_n < per_window or not self._pool_fits(raw, cal)) or dominant:
                self.pool_n = 0
            elif strong or (better and far):
                self.pool_streak += 1
                if self.pool_streak < per_window:
                    return
                self.pool_n = 0                    # the data moved on: start again from this trial
        self.pool_streak = 0
        self.pool_n += 1
        self.pool_mean += (member - self.pool_mean) / min(self.pool_n, self.POOL_WINDOWS * per_window)
        S, F = det_one(self.pool_mean[3:12].reshape(3, 3), float(self.pool_mean[12]))
        pooled = replace(cal, hard_iron=self.pool_mean[:3].copy(), soft_iron=S, field=F)
        # the uncertainty is one window's figure: recomputed when the pool restarts and once per window
        # turnover (0.3 ms each at W = 512, about a sixth of the calibrator's time if done every trial)
        fresh = self.pool_n % per_window == 1 % per_window or self.accepted is None or self.accepted.uncertainty is None
        self._accept(pooled, raw, switched=self.pool_n == 1,
                     uncertainty=None if fresh else self.accepted.uncertainty)

    def _pool_fits(self, raw, cal) -> bool:
        """Whether the accepted calibration passes the fit gates (outlier fraction, residual) on the
        window, judged as a trial would be (the window's condition is the trial's: it does not depend
        on the calibration)."""
        a = self.accepted
        quality = quality_figures((raw - a.hard_iron) @ np.asarray(a.soft_iron).T, a.field, cal.quality["condition"])
        rejection = evaluate(quality, a.field, self.unit, self.rules)
        return rejection is None or not ("residual" in rejection.failed or "outliers" in rejection.failed)

    def _accept(self, cal, raw, switched=True, uncertainty=None):
        if uncertainty is None:
            uncertainty = calibration_uncertainty(raw, cal.hard_iron, cal.soft_iron, cal.field)
        self.accepted = replace(cal, uncertainty=uncertainty)
        self.switches += int(switched)
        if self.first_accepted_at is None:
            self.first_accepted_at = cal.samples_seen

    def _needs_confirmation(self, b, F) -> bool:
        """A trial that passes the gates is confirmed by a cold start unless it is the calibration
        confirmed last (within the disagreement tolerance): steady streams pay nothing."""
        if self._confirmed is None:
            return True
        b0, F0 = self._confirmed
        tol = self.rules.max_disagreement_rel * abs(F)
        return not (np.linalg.norm(b - b0) <= tol and abs(F - F0) <= tol)

    def _cold_start_disagreement(self, raw, b, F):
        """Run batch MKC-EM from scratch on the window (in the stream's own state, by the kernels).

        Returns (disagreement, cold): if the cold start agrees, the warm state is restored
        (nothing changes); otherwise the stream continues from the cold start, and `cold` is its
        (b, S, F, quality, sigma, d) - or None if the cold start gave no ellipsoid.
        """
        st = self.stream.kernel_state
        saved = {k: v.copy() for k, v in st.items()}
        # from the window's own trimmed sphere (a high-breakdown start, independent of the warm
        # trial) and from WLS; the one the window's likelihood prefers is kept (_better_cold_start).
        # Only WLS when the window gives no sphere around the features' origin.
        fit = robust_sphere_fit(raw) if raw.shape[0] >= 8 else None
        theta0 = None if fit is None else sphere_theta((fit[0] - self.c0) / self.s0, fit[1] / self.s0)
        if theta0 is None:
            K.cold_start(*self.stream.kernel_args, self.COLD_START_ROUNDS)
        else:
            self._better_cold_start(saved, theta0)
        try:
            geom = raw_geometry(geometry_from_theta(st["theta"]), Normalisation(self.c0.copy(), self.s0))
            bc, Sc, Fc = calibration_from_geometry(geom)
        except (EllipsoidError, np.linalg.LinAlgError):
            return np.inf, None
        disagreement = max(float(np.linalg.norm(bc - b)), abs(Fc - F))
        if disagreement <= self.rules.max_disagreement_rel * abs(F):
            for k, v in st.items():
                v[...] = saved[k]
            return disagreement, None
        count = raw.shape[0]
        dc = float(st["d"][0])
        qc = quality_figures((raw - bc) @ Sc.T, Fc, weighted_condition(st["X"][:count, 0, :], st["C"][:count, 0] * dc * dc))
        return disagreement, (bc, Sc, Fc, qc, float(st["sigma"][0]), dc)

    def _better_cold_start(self, saved, theta0):
        """Batch MKC-EM from the sphere start theta0 and from WLS, each from the warm state `saved`;
        the stream's state is left at the one with the lower E-step objective at its final theta,
        sigma, d and truncation (kernels.window.window_objective: the window's mean negative
        log-likelihood of the truncated induced pdf, eqs. (29)-(31)); the sphere start on a tie.

        Why two starts: under heavy bursts (a quarter of the window or more) the window's MKC-EM has
        more than one fixed point, and either start can fall into a wrong one that passes every gate
        (synthetic seed 3279 at 25%: the sphere start's mode 15 uT off, WLS's 0.07). EM from several
        starts, kept by likelihood, is the standard cure; the likelihood is what both runs maximise.
        A run that ends singular or with a non-finite objective counts as worst.
        """
        st = self.stream.kernel_state
        args = self.stream.kernel_args

        def score(status):
            if status not in (K.OK, K.NOT_CONVERGED):
                return math.inf
            f = K.window_objective(st["icfg"], st["fcfg"], st["X"], st["Y"], st["theta"], st["sigma"], st["d"], st["a"],
                                   st["ebuf"], st["cnt"])
            return f if math.isfinite(f) else math.inf

        f_sphere = score(K.cold_start_at(*args, self.COLD_START_ROUNDS, theta0))
        from_sphere = {k: v.copy() for k, v in st.items()}
        for k, v in st.items():
            v[...] = saved[k]
        f_wls = score(K.cold_start(*args, self.COLD_START_ROUNDS))
        if not f_wls < f_sphere:
            for k, v in st.items():
                v[...] = from_sphere[k]

    def _try_final_normalisation(self, raw, seen, esteps):
        fit = robust_sphere_fit(raw) if len(raw) >= 8 else None
        cov = 0.0
        spread = sphere_spread(raw, *fit) if fit is not None else np.inf
        if fit is not None and spread <= self.MAX_SPHERE_SPREAD:
            b, F = fit
            cov = sphere_coverage(raw - b)
        if fit is not None and spread > self.MAX_SPHERE_SPREAD:
            self.last_rejection = Rejection("waiting_motion", motion_wait_reason(spread, self.MAX_SPHERE_SPREAD),
                                            values={"spread": spread})
        elif fit is None or cov < self.MIN_SPHERE_COVERAGE:
            self.last_rejection = Rejection("waiting_coverage", coverage_wait_reason(cov, self.MIN_SPHERE_COVERAGE),
                                            values={"coverage": cov})
        if fit is None or spread > self.MAX_SPHERE_SPREAD or cov < self.MIN_SPHERE_COVERAGE:
            ev = CheckpointEvent(seen, esteps, False, self.last_reason)
            if self.keep_history:
                self.history.append(ev)
            return ev
        self._set_normalisation(b, F, restart=True)
        self.provisional = False
        return None

    def _set_normalisation(self, c0, s0, theta=None, restart=False):
        st = self.stream.kernel_state
        self.c0, self.s0 = np.asarray(c0, dtype=np.float64).copy(), float(s0)
        count = int(st["cnt"][K.C_COUNT])
        MW.refeature_window(st["X"], self.raw, count, self.c0, np.float64(self.s0), self._xk)
        MW.recount_cells(self.raw, count, self.c0, self.slot_cell, self.cell_count)
        args = (st["icfg"], st["fcfg"], st["X"], st["Y"], st["C"], st["A"], st["b"], st["theta"], st["sigma"], st["d"])
        if restart:
            # (c0, s0) is the window's trimmed sphere fit: start from that sphere, the unit sphere here
            K.restart_at(*args, st["Hes"], st["L"], st["D"], st["xs"], st["tprev"], st["ebuf"], st["cnt"], st["fst"],
                         UNIT_SPHERE_THETA)
            K.estep_window(st["icfg"], st["fcfg"], st["X"], st["Y"], st["theta"], st["sigma"], st["d"], st["a"],
                           st["Hes"], st["R"], st["ebuf"], st["cnt"], st["fst"])
            K.rebuild(*args, st["L"], st["D"], st["xs"], st["tprev"], st["cnt"], st["fst"])
        else:
            st["theta"][:] = theta
            K.rebuild(*args, st["L"], st["D"], st["xs"], st["tprev"], st["cnt"], st["fst"])

    def _maybe_renormalise(self, geom, b, F):
        """Re-centre the features on the trial centre and radius when they drift by > 10%."""
        if not (np.linalg.norm(b - self.c0) > 0.1 * self.s0 or abs(F / self.s0 - 1.0) > 0.1):
            return
        # the trial quadric in the new coordinates: (m - b)^T M (m - b) = 1 -> A' = s^2 M, B' = 0
        Ap = float(F) ** 2 * geom.M
        theta = np.array([Ap[0, 0], Ap[1, 1], Ap[2, 2], 2 * Ap[0, 1], 2 * Ap[0, 2], 2 * Ap[1, 2], 0.0, 0.0, 0.0])
        self._set_normalisation(b, F, theta=theta)

    # -- use -------------------------------------------------------------------------------
    def apply(self, raw):
        """Calibrate raw samples with the ACCEPTED calibration only."""
        if self.accepted is None:
            raise NotCalibratedError(f"no calibration accepted yet ({self.status_reason()})")
        return self.accepted.apply(raw)

    @property
    def last_reason(self) -> str:
        """The last checkpoint's rejection sentence, '' when it was accepted."""
        return "" if self.last_rejection is None else self.last_rejection.text

    def status(self) -> Rejection | None:
        """None when a calibration is accepted and the last trial passed, else why not (yet)."""
        if self.s0 <= 0:
            return Rejection("warming_up", f"warming up: {len(self._pending)}/{self.init_samples} samples",
                             values={"samples": len(self._pending), "needed": self.init_samples})
        snap = self.stream.snapshot()
        if snap.status == "warming up":
            need = self.stream.config.effective_min_samples
            return Rejection("warming_up", f"warming up: {snap.window_count}/{need} samples in the window",
                             values={"samples": snap.window_count, "needed": need})
        if self.stream.esteps == 0 and snap.status == "normal equations singular":
            # no checkpoint can come: the samples lie on a curve or a plane, never on an ellipsoid
            return Rejection("not_ellipsoid", degenerate_reason())
        return self.last_rejection

    def status_reason(self) -> str:
        r = self.status()
        return "accepted" if r is None else r.text

    def weights(self):
        """(raw samples of the window, their kernel weights): low weight = treated as disturbed."""
        raw, count = self._window_raw()
        return raw.copy(), self.stream.view("C")[:count, 0] * self.stream.view("d")[0] ** 2

    def counts(self):
        seen, rejected = self.stream.samples_seen, self.stream.samples_rejected
        return {"samples": seen + rejected + len(self._pending), "bad_frames": rejected,
                "drops": 0, "gaps": 0}

    def nbytes(self) -> int:
        return self.stream.nbytes() + self.raw.nbytes + self.slot_cell.nbytes + self.slot_age.nbytes + \
            self.cell_count.nbytes + self.c0.nbytes + 8 + self._xk.nbytes + self._yk.nbytes
