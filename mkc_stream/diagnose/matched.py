"""Matched tests: one test per deterministic (mean) effect of the library.

The gap index (:mod:`.gap`) is an omnibus over hundreds of statistics: it is blind to a small
slow change of the hard iron (a drift, a thermal offset under a ramp) that a test knowing the
change's form sees at several sigma. For every mean effect (a term linear in its parameters
once its nonlinear setting is fixed, :mod:`.forms`) this module asks the direct question: how
much does the weighted residual sum of squares of the baseline drop when the term is added?

* Statistic: the score statistic Q = g' A^-1 g of the term's columns made orthogonal to the
  calibration's (what the ellipsoid and dip absorb is no evidence), on all samples, maximised
  over the form's settings (thermal lags, step times ...). For one setting and white noise
  Q ~ chi2_k. All the columns (the calibration's and the term's) are read at
  :func:`.model.noise_free_point` (the neighbours' field put on the fitted sphere), not at the
  noisy sample: a column read at the sample carries the noise the sample's residual is made
  of, and the cubic columns, about 95% of which the ellipsoid's absorb, keep that shared noise
  through the orthogonalisation; on a noisy or long null that alone made a cubic term fire.
* Null: the same on every replica of the baseline (simulated without the effect, projected
  through the same fit, the same search over settings), so the search, the bursts and the
  masks are paid for in the null. The cube root of a (scaled) chi-square is nearly normal
  (Wilson-Hilferty), also for a maximum over settings: Q^(1/3) is standardised on the
  replicas and read on a Student-t tail with R - 1 degrees of freedom (a prediction interval
  for one more draw when the replica mean and spread are themselves estimated from R draws:
  40 replicas cannot resolve a 0.1% tail empirically).
* Level: a test fires below ALPHA / (number of tests), Bonferroni, so the matched tests add at
  most ALPHA to the gap index's 1% false alarms.

Why not held out: the held-out statistics of the two folds (each fold's fit predicting the
other's residual) are strongly correlated, and standardising their sum on the replicas loses
about a third of the signal-to-noise ratio against this score test; the replicas, which repeat
the whole search, are what guards against a flexible form fitting noise. Selection and shrink
elsewhere stay held out.

The latency test also reads the gyroscope when there is one (:mod:`.gyro_timing`: the
magnetometer's rotation against the gyroscope's, independent of the channels' noise): its p-value
is the smaller of the two, doubled (Bonferroni over the two views), so the test keeps its level.
No other mean effect of the library shifts that timing, so the gyroscope's evidence is the same
given any other terms (a hysteresis also lags the rotation; it is not modelled there).

Conditional tests (the same with other terms added to the base) say whether one effect
explains another's evidence away: the basis of the ambiguity between a thermal offset and a
drift under a temperature ramp, and of the matched shrink (how much of the fired evidence an
effect removes).
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from .forms import FORMS, MeanForm
from .model import INLIER_K, RIDGE, channels, noise_free_point, project

#: total false-alarm budget of the matched tests (Bonferroni over the tests)
ALPHA = 0.01
#: null level of max(Z, 0)^2 for a standardised Z (the discrepancy of one unfired test)
NULL_LEVEL = 0.5
#: largest standardised statistic reported (a p-value below ~1e-300 has no finite t on R - 1
#: degrees of freedom; the gyroscope's timing test reaches t ~ 100 on a 5 ms latency)
T_CAP = 50.0


def mean_effects(names):
    """The mean-form effects among names, one per observable (cross_axis is misalignment's
    observable: tested once, under whichever of the two is in the library)."""
    out = []
    for n in names:
        f = FORMS[n]
        if not isinstance(f, MeanForm):
            continue
        if f.alias_of is not None and f.alias_of in names:
            continue
        out.append(n)
    return out


class MatchedTests:
    def __init__(self, eng, ev, names, gyro=None):
        """eng: the Engine; ev: the baseline's evaluation (with ev.rep_raw); names: the
        testable mean effects to test; gyro: the gyroscope timing test
        (:func:`.gyro_timing.gyro_delay`), which joins the latency test when testable."""
        self.eng, self.ev = eng, ev
        self.gyro = gyro if gyro and gyro.get("testable") else None
        frame, base = eng.frame, eng.base
        sigma = base.sigma
        self.names = [n for n in names if FORMS[n].designs(eng.env)]
        fit = base.fit                  # the baseline fitted on all samples
        allm = np.ones(frame.n, dtype=bool)
        rep = project(ev.rep_raw, ev.rep_valid, fit.X, allm, sigma, base.valid)       # (R, N, C)
        E = np.concatenate([fit.e[None], rep], axis=0) / sigma[None, None, :]
        W = np.concatenate([base.valid[None], ev.rep_valid], axis=0) & (np.abs(E) < INLIER_K)
        self.M, N, C = E.shape
        self.EW = (E * W).reshape(self.M, N * C)          # weighted residuals, real first
        self.w0 = W[0].reshape(N * C).astype(np.float64)  # the real recording's weights (shared Gram)
        self.fit, self.NC = fit, N * C
        # every column of the test (the base's, which the term is made orthogonal to, and the
        # term's) is read where the sample's own noise is not (see noise_free_point; the fit's
        # columns fit.X are read there too): the real residual is that noise, and a column
        # sharing it correlates with it on the real recording alone (each replica's noise is
        # its own), a bias no null can pay for
        self.m_read = noise_free_point(fit.m_corr, fit.state)
        self.X0 = (fit.X / sigma[None, :, None]).reshape(N * C, -1)
        self.J = channels(self.m_read, frame, fit.state).J
        self._cols = {}
        self._cache = {}
        self.R = self.M - 1

    # -- columns ----------------------------------------------------------------------------
    def columns(self, name):
        """[(design, X (N*C, k) scaled by sigma)] of every setting of an effect."""
        if name not in self._cols:
            form, env = FORMS[name], self.eng.env
            s = self.eng.base.sigma
            out = []
            for des in form.designs(env):
                G = form.G(env, des)(self.eng.frame, self.m_read, self.fit.state)
                X = -np.einsum("nck,nkp->ncp", self.J, G) / s[None, :, None]
                out.append((des, X.reshape(self.NC, -1)))
            self._cols[name] = out
        return self._cols[name]

    # -- the test ---------------------------------------------------------------------------
    def _gram(self, A, B):
        return (A * self.w0[:, None]).T @ B

    def _scores(self, name, given):
        """Score statistic Q (M,) of one effect (real first, then the replicas): the weighted
        RSS improvement of adding its term to the base (baseline + given terms) at the best
        setting, per data set, and the real data's setting index."""
        Xb = self.X0
        if given:
            Xb = np.concatenate([Xb] + [self.columns(g)[self.design_index(g)][1] for g in given], axis=1)
        Abb = self._gram(Xb, Xb)
        Abb += RIDGE * np.trace(Abb) / Abb.shape[0] * np.eye(Abb.shape[0])
        best = np.full(self.M, -np.inf)
        pick = np.zeros(self.M, dtype=int)
        for i, (_, Xt) in enumerate(self.columns(name)):
            # the term's part the base cannot absorb
            B = np.linalg.solve(Abb, self._gram(Xb, Xt))
            Xo = Xt - Xb @ B
            A = self._gram(Xo, Xo)
            k = A.shape[0]
            A += RIDGE * max(np.trace(A) / k, 1e-300) * np.eye(k)
            # Xo is orthogonal to the base, so this is also the gradient on the residual after
            # the base (baseline + given terms) is refitted
            g = self.EW @ Xo
            Q = np.sum(g * np.linalg.solve(A, g.T).T, axis=1)
            better = Q > best
            best = np.where(better, Q, best)
            pick = np.where(better, i, pick)
        return best, int(pick[0])

    def design_index(self, name):
        return self.result(name)["design"]

    def result(self, name, given=()):
        """{"Q": real statistic, "t": standardised, "p": one-sided p-value, "design": setting}."""
        key = (name, tuple(sorted(given)))
        if key not in self._cache:
            Q, des = self._scores(name, list(key[1]))
            # Wilson-Hilferty: the cube root of a (scaled) chi-square is nearly normal, also for
            # the maximum over a grid of settings; standardised on the replicas and read on a
            # Student-t tail (the replica mean and spread are estimated from R draws)
            S = np.cbrt(np.maximum(Q, 0.0))
            rep = S[1:]
            R = rep.size
            m, s = float(np.mean(rep)), float(np.std(rep, ddof=1))
            t = (float(S[0]) - m) / (max(s, 1e-12) * np.sqrt(1.0 + 1.0 / R))
            out = {"Q": float(Q[0]), "t": t, "p": float(stats.t.sf(t, R - 1)), "design": des}
            if name == "latency" and self.gyro is not None:
                out = self._with_gyro(out, R)
            self._cache[key] = out
        return self._cache[key]

    def _with_gyro(self, out, R):
        """The latency test read in the channels and against the gyroscope: the smaller
        p-value doubled (Bonferroni over the two), back on the channels' t scale."""
        g = self.gyro
        log_pg = float(np.log(2.0) + stats.t.logsf(abs(g["t"]), g["dof"]))       # two-sided
        log_pc = float(stats.t.logsf(out["t"], R - 1))
        log_p = min(0.0, float(np.log(2.0)) + min(log_pg, log_pc))
        p = float(np.exp(log_p))
        t = float(stats.t.isf(p, R - 1)) if p > 1e-300 else T_CAP
        return {**out, "t": min(t, T_CAP), "p": p, "t_channels": float(out["t"]), "p_channels": float(out["p"]),
                "t_gyro": float(g["t"]), "p_gyro": float(np.exp(log_pg))}

    @property
    def level(self):
        """Per-test level (Bonferroni)."""
        return ALPHA / max(len(self.names), 1)

    def fired(self, given=(), among=None):
        among = self.names if among is None else among
        return [n for n in among if n not in given and self.result(n, given)["p"] < self.level]

    def discrepancy(self, names, given=()):
        """Sum over names of max(t, 0)^2 given the terms in ``given`` (0 for those in it)."""
        return float(sum(max(self.result(n, given)["t"], 0.0) ** 2 for n in names if n not in given))

    def shrink(self, names, given):
        """Fraction of the fired evidence (names) that adding ``given`` removes, against its
        null level NULL_LEVEL per test."""
        d0 = self.discrepancy(names)
        ex = d0 - NULL_LEVEL * len(names)
        if not ex > 0:
            return float("nan")
        return float((d0 - self.discrepancy(names, given)) / ex)

    def summary(self):
        keys = ("t", "p", "t_channels", "p_channels", "t_gyro", "p_gyro")
        return {n: {k: self.result(n)[k] for k in keys if k in self.result(n)} for n in self.names}
