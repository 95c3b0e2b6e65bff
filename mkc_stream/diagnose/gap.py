"""Calibrated z-scores and the gap index.

z = (real - replica mean) / replica sd, per statistic, with a floor on the sd (a statistic that
never varies in the replicas, e.g. the timestamp jitter of a perfect clock, would otherwise
divide by zero) and clipped to +-Z_CAP so one wild statistic cannot swamp the index.

Families are the panel's families split by channel ("sphere/dip", "aux:temp/norm" ...). Each
family is scored by the mean of its largest tenth of z^2 (an unmodelled effect usually moves a
few statistics of a family a lot, not all of them a little; averaging all of them would dilute
it), divided by that score's mean over the replicas scored against each other (leave-one-out), so
every family scores about 1 when the simulator matches. The gap index is the square root of
the root mean square of the family scores, divided by its leave-one-out median: about 1 when
the simulator matches; it grows like |z| (so "half the gap" means half the discrepancy), and
one family far off pulls it up more than many families slightly off (the plain mean would
dilute a gap that shows in one family among ~25). These choices were compared on simulated
recordings with and without weak effects (power at a fixed false-alarm rate). The alarm
threshold is the 99% point of a lognormal fitted to the leave-one-out indices.

A model whose stochastic effects widen its replicas adds, per statistic, the log of the
variance ratio (the Dawid-Sebastiani score's penalty) to z^2, so it cannot close a gap just by
becoming vague.
"""
from __future__ import annotations

import numpy as np

Z_CAP = 30.0
TOP_FRACTION = 0.1
TOP_MIN = 3                   # at least this many statistics make a family's score (fewer: heavy tails)
POWER = 2.0                   # power mean over families: between the mean (dilutes) and the max (noisy)
NULL_QUANTILE_Z = 2.326       # 99% one-sided


def spread(reps, floors):
    """Replica standard deviation per statistic, floored."""
    fin = np.isfinite(reps)
    cnt = fin.sum(axis=0)
    mu = np.where(cnt > 0, np.nansum(reps, axis=0) / np.maximum(cnt, 1), np.nan)
    dev = np.where(fin, reps - mu, 0.0)
    return np.maximum(np.sqrt(np.sum(dev * dev, axis=0) / np.maximum(cnt - 1, 1)), floors)


def zscores(x, reps, floors):
    """x (K,), reps (R, K) -> z (K,) (NaN where x or too many replicas are undefined)."""
    R = reps.shape[0]
    fin = np.isfinite(reps)
    cnt = fin.sum(axis=0)
    mu = np.where(cnt > 0, np.nansum(reps, axis=0) / np.maximum(cnt, 1), np.nan)
    z = (x - mu) / spread(reps, floors)
    z[(cnt < max(3, R // 2)) | ~np.isfinite(x)] = np.nan
    return np.clip(z, -Z_CAP, Z_CAP)


def family_key(family, channel):
    """The gap index's family name of a statistic: "sphere/norm", "aux:temp/dip", "raw" ..."""
    return family if family in ("timing", "raw") else f"{family}/{channel}"


class GapIndex:
    def __init__(self, families, channels, off=None):
        """off: family name -> the reason it is not testable (None when it is); such a family
        scores NaN, so neither the index nor its null reads it."""
        keys = [family_key(f, c) for f, c in zip(families, channels)]
        self.names = list(dict.fromkeys(keys))
        self.off = {n: why for n in self.names if off is not None and (why := off(n))}
        self.idx = np.array([self.names.index(k) for k in keys])
        self.order = np.argsort(self.idx, kind="stable")
        self.bounds = np.searchsorted(self.idx[self.order], np.arange(len(self.names) + 1))
        self.norm = np.ones(len(self.names))
        self.scale = 1.0

    def family_scores(self, z, w, penalty=None):
        """Mean of the top tenth (by weight) of z^2 (+ penalty) in each family; NaN for empty ones."""
        d = z * z
        if penalty is not None:
            d = d + np.nan_to_num(penalty)
        ok = np.isfinite(d) & (w > 0)
        out = np.full(len(self.names), np.nan)
        d, w, ok = d[self.order], w[self.order], ok[self.order]
        for f in range(len(self.names)):
            if self.names[f] in self.off:
                continue
            a, b = self.bounds[f], self.bounds[f + 1]
            sel = ok[a:b]
            if not sel.any():
                continue
            df, wf = d[a:b][sel], w[a:b][sel]
            o = np.argsort(-df)
            df, wf = df[o], wf[o]
            need = min(max(float(TOP_MIN), TOP_FRACTION * wf.sum()), wf.sum())
            cw = np.cumsum(wf)
            take = np.minimum(wf, np.maximum(need - (cw - wf), 0.0))
            out[f] = float(np.sum(take * df) / need)
        return out

    def combine(self, scores):
        """Power mean of the normalised family scores, square-rooted so that the index grows like
        |z| (not z^2): a model that halves the discrepancy closes half of the excess gap."""
        s = scores / self.norm
        s = s[np.isfinite(s)]
        return float(np.sqrt(np.mean(s ** POWER) ** (1.0 / POWER)) / self.scale) if s.size else float("nan")

    def index(self, z, w, penalty=None):
        return self.combine(self.family_scores(z, w, penalty))

    def loo_scores(self, reps, w, floors):
        """Family scores of each replica against the others: (R, families)."""
        R = reps.shape[0]
        out = np.empty((R, len(self.names)))
        for i in range(R):
            others = np.delete(reps, i, axis=0)
            out[i] = self.family_scores(zscores(reps[i], others, floors), w)
        return out

    def calibrate(self, reps, w, floors):
        """Per-family and overall normalisation from the leave-one-out null; returns the null indices."""
        fs = self.loo_scores(reps, w, floors)
        cnt = np.isfinite(fs).sum(axis=0)          # (a family left out is NaN throughout)
        # the mean, not the median: small families are skewed
        mean = np.where(cnt > 0, np.nansum(fs, axis=0) / np.maximum(cnt, 1), np.nan)
        # at least 1 (z^2 units): a family that never moves in the replicas (all z ~ 0 by
        # construction) must not turn a real deviation into an astronomically large score
        self.norm = np.where(np.isfinite(mean), np.maximum(mean, 1.0), 1.0)
        self.scale = 1.0
        null = np.array([self.combine(f) for f in fs])
        m = np.nanmedian(null)
        self.scale = float(m) if np.isfinite(m) and m > 0 else 1.0
        return null / self.scale


def threshold(null):
    g = np.log(np.maximum(null[np.isfinite(null)], 1e-6))
    if g.size < 5:
        return float("inf")
    return float(np.exp(np.mean(g) + NULL_QUANTILE_Z * np.std(g, ddof=1)))


def shrink(g0, g1, floor=1.0):
    """Fraction of the excess gap (g0 - 1) closed by a model with gap g1."""
    ex = g0 - floor
    if not np.isfinite(ex) or ex <= 0:
        return float("nan")
    return float((g0 - g1) / ex)
