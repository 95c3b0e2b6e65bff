"""The power signal's delay in the flight fit: the delayed column, the two-pass search over it, and
the delay's standard error.

The field of the power wiring is K c(t - tau) (vector_fit's module doc): the magnetometer sees the
logged signal c tau seconds late, or, for a negative tau, the logged signal is the late one (a filtered
or late-logged current sensor; decisions/0030).
"""
from __future__ import annotations

import math

import numpy as np

#: Grid steps of the delay search, s: a coarse pass over the whole range, then a fine one around its
#: best point, refined by a parabola through the best point and its neighbours.
DELAY_COARSE = 0.025
DELAY_STEP = 0.005
#: A delay whose 95% interval reaches further than this each side (s) is not reported, in the flight
#: fit and in the diagnosis's current test alike.
DELAY_DETERMINED = 0.1


def delayed(t, c, tau) -> np.ndarray:
    """c(t_k - tau) by linear interpolation (held at the ends); c (N, n_c)."""
    if tau == 0.0 or c.shape[1] == 0:
        return c
    return np.stack([np.interp(t - tau, t, c[:, j]) for j in range(c.shape[1])], axis=1)


def profile_search(values, evaluate):
    """Minimise evaluate(v) over the grid values, refined by a parabola: (best, [(v, J)])."""
    J = np.array([evaluate(v) for v in values])
    k = int(np.argmin(J))
    best = float(values[k])
    if 0 < k < len(values) - 1:
        j0, j1, j2 = J[k - 1], J[k], J[k + 1]
        den = j0 - 2 * j1 + j2
        if den > 0:
            best = float(values[k] + 0.5 * (j0 - j2) / den * (values[1] - values[0]))
    return best, list(zip(map(float, values), map(float, J)))


def search_delay(max_delay, evaluate):
    """The delay search (vector_fit's module doc): (tau, [(tau, J)] over both passes, sorted), with
    |tau| <= max_delay."""
    coarse = profile_search(np.arange(-max_delay, max_delay + 1e-9, DELAY_COARSE), evaluate)[1]
    centre = min(coarse, key=lambda p: p[1])[0]
    fine = np.arange(centre - DELAY_COARSE, centre + DELAY_COARSE + 1e-9, DELAY_STEP)
    fine = fine[np.abs(fine) <= max_delay + 1e-9]
    tau, prof = profile_search(fine, evaluate)
    return min(max(tau, -max_delay), max_delay), sorted(dict(coarse + prof).items())


def delay_standard_error(t, c, fit, block_s) -> float:
    """Cluster-robust standard error (s) of the fitted delay, by linearising the power term about it:
    K c(t - tau - e) ~ K c(t - tau) - e D, D_k = K dc/dt(t_k - tau), so e is the weighted regression of
    the residuals E on -D (weights C = w / d^2, the final kernel's), with a sandwich over time blocks
    of block_s seconds (as vector_fit's parameter_covariance). D is taken as orthogonal to the other
    regressors (a stationary signal and its rate are uncorrelated). A smooth power signal (a flat objective in the
    delay) gives a large error: the search's choice is then not a measurement. nan without power terms."""
    if c.shape[1] == 0 or fit.delay_s is None or t.shape[0] < 3:
        return math.nan
    with np.errstate(divide="ignore", invalid="ignore"):       # repeated timestamps: no rate there
        dc = np.gradient(delayed(t, c, fit.delay_s), t, axis=0)
    D = np.nan_to_num(dc, nan=0.0, posinf=0.0, neginf=0.0) @ np.asarray(fit.K).T
    C = fit.weights / (np.asarray(fit.d) ** 2)[None, :] if np.all(np.isfinite(fit.sigma)) else np.ones_like(D)
    den = float(np.sum(C * D * D))
    if not den > 0:
        return math.inf
    blk = np.floor((t - t[0]) / block_s).astype(np.int64)
    score = np.bincount(blk, np.sum(C * D * fit.residuals, axis=1))
    G = score.size
    return math.sqrt(float(np.sum(score ** 2)) * G / max(G - 1, 1)) / den
