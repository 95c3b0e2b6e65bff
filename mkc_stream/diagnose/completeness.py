"""Is an explanation complete? After the selection, does the residual still follow an aux signal?

The gap index is an omnibus: once the selected effects bring it to its null level, a small
remainder that follows a recorded aux signal can be left unseen. That is the signature of an
effect whose form is not in the library but whose cause is recorded: with the current's own
effect missing, a throttle-proportional hard iron absorbs the part of the current that follows
the throttle, and the other loads' share (a few amperes switching on and off) stays in the
residual, far below the gap index's reach but at t > 3 for a test that knows the signal.

Statistic: the score statistic of :mod:`.matched` for a generic term, a hard-iron offset linear
in the (standardised) aux signal (three columns), made orthogonal to the calibration, to a
linear trend of the hard iron and to the selected mean effects' terms at their chosen settings:
Q = g' A^-1 g on the weighted residual. Not run when a random walk or coloured noise is
selected (see :func:`aux_left`).

Null: the same statistic with the aux signal circularly shifted in time against the residual
(shifts between a tenth and nine tenths of the recording). A shift keeps both series' own
time structure and breaks only their alignment, so what a replica-based null would wrongly
call a dependence is paid for here: a slow noise selected for what it is, or a selected step
whose grid time is a few seconds off (its leftover pulse meets a piecewise-constant throttle
by chance far more often than white noise does). Q^(1/3) standardised on the shifts, read on a
Student-t tail (Wilson-Hilferty, as in :mod:`.matched`). Level: ``matched.ALPHA`` over the aux
signals (Bonferroni). Aux signals are correlated (a board warms with its current), so a signal
is named only when it is still significant given the stronger ones already named.

A named signal turns "explained" into "partially explained": the data show a dependence the
selected effects leave, and the report names the signal.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from .engine import CATCH_ALL
from .matched import ALPHA
from .model import INLIER_K, RIDGE, channels, noise_free_point

#: share of an aux term's weighted norm it must keep outside the base to be tested (a term the
#: selected effects span, like the current's own effect against the current, has nothing left)
FREE = 1e-6
#: circular shifts of the null
SHIFTS = 100


class _Design:
    """The baseline's weighted residual and columns, with the selected mean terms added."""

    def __init__(self, eng, terms):
        frame, base = eng.frame, eng.base
        fit, s = base.fit, base.sigma
        N, C = fit.e.shape
        E = fit.e / s[None, :]
        W = base.valid & (np.abs(E) < INLIER_K)
        self.w = W.reshape(-1).astype(np.float64)
        self.e = np.where(W, E, 0.0).reshape(-1)
        # columns read where the sample's own noise is not (as the fit's: .model.noise_free_point)
        m_read = noise_free_point(fit.m_corr, fit.state)
        self.J = channels(m_read, frame, fit.state).J
        self.s, self.N, self.C = s, N, C
        cols = [(fit.X / s[None, :, None]).reshape(N * C, -1)]
        # a linear trend of the hard iron belongs to no aux signal: without it in the base, a
        # ramp-shaped signal (a battery's voltage) would stand for any slow residual
        tt = (frame.t - frame.t.mean()) / max(float(np.ptp(frame.t)), 1e-300)
        cols.append(self.raw_columns(tt[:, None, None] * np.eye(3)[None]))
        cols += [self.raw_columns(t.G(frame, m_read, fit.state)) for t in terms]
        self.base = np.concatenate(cols, axis=1)

    def raw_columns(self, G):
        """(N*C, k) channel columns of a raw-domain perturbation G (N, 3, k), in noise units."""
        return (-np.einsum("nck,nkp->ncp", self.J, G) / self.s[None, :, None]).reshape(self.N * self.C, -1)

    def aux_columns(self, a):
        a = (a - a.mean()) / max(float(a.std()), 1e-300)
        return self.raw_columns(a[:, None, None] * np.eye(3)[None])

    def gram(self, A, B):
        return (A * self.w[:, None]).T @ B

    def stats(self, Xb, cols):
        """Q of each term in cols (list of (N*C, k)) against the residual, given the base Xb."""
        Abb = self.gram(Xb, Xb)
        Abb += RIDGE * np.trace(Abb) / Abb.shape[0] * np.eye(Abb.shape[0])
        r = self.e - Xb @ np.linalg.solve(Abb, self.gram(Xb, self.e[:, None]))[:, 0]
        out = np.zeros(len(cols))
        for i, Xt in enumerate(cols):
            Xo = Xt - Xb @ np.linalg.solve(Abb, self.gram(Xb, Xt))
            d = 1.0 / np.sqrt(np.maximum(np.diag(self.gram(Xt, Xt)), 1e-300))
            lam, V = np.linalg.eigh(d[:, None] * self.gram(Xo, Xo) * d[None, :])
            keep = lam > FREE
            if not keep.any():
                continue
            Xf = Xo @ (d[:, None] * V[:, keep])
            g = self.gram(Xf, r[:, None])[:, 0]
            out[i] = float(g @ np.linalg.solve(self.gram(Xf, Xf), g))
        return out


def _test(des, Xb, a, shifts):
    """(t, p) of the aux signal a against the residual, on its circular shifts."""
    Q = des.stats(Xb, [des.aux_columns(np.roll(a, k)) for k in [0] + list(shifts)])
    S = np.cbrt(np.maximum(Q, 0.0))
    K = S.size - 1
    m, sd = float(np.mean(S[1:])), float(np.std(S[1:], ddof=1))
    t = (float(S[0]) - m) / (max(sd, 1e-12) * np.sqrt(1.0 + 1.0 / K))
    return t, float(stats.t.sf(t, K - 1))


def aux_left(eng, final, selected, seed=0):
    """{aux name: {"t", "p", "fired"}} for every recorded aux signal, given the selected mean
    effects (final: the Evaluation of the selected model, whose terms carry their settings);
    t and p are each signal's own test, "fired" also needs it given the stronger fired signals.
    Empty when the recording has no aux signal, or when a random walk or coloured noise is
    selected: the residual's slow part is then noise by hypothesis, a few correlation times
    long, and its chance alignment with a slow aux signal is no evidence (a 40-80 s
    Gauss-Markov noise over 500 s gave t = 4.0-5.2 against throttle, current and voltage on the
    circular shifts, whose ~8 independent positions the t tail over-counts)."""
    aux = eng.frame.aux
    if not aux or any(n in CATCH_ALL for n in selected):
        return {}
    des = _Design(eng, [t for t in final.cand.terms if t.name in selected])
    N = eng.frame.n
    rng = np.random.default_rng(30_000 + seed)
    shifts = rng.integers(N // 10, N - N // 10, SHIFTS)
    level = ALPHA / len(aux)
    res = {n: _test(des, des.base, np.asarray(a, dtype=np.float64), shifts) for n, a in aux.items()}
    named, Xb = [], des.base
    for n in sorted((n for n in aux if res[n][1] < level), key=lambda n: -res[n][0]):
        if not named or _test(des, Xb, np.asarray(aux[n], dtype=np.float64), shifts)[1] < level:
            named.append(n)
            Xb = np.concatenate([Xb, des.aux_columns(np.asarray(aux[n], dtype=np.float64))], axis=1)
    return {n: {"t": res[n][0], "p": res[n][1], "fired": n in named} for n in aux}
