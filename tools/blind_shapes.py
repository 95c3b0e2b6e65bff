"""How much of a trial's injected change a wrong slow-offset form could follow, noise-free.

The blind benchmark's line "the best wrong deterministic effect outside the declared pair closes
at most 0.3 of the gap" asks the diagnosis to keep wrong forms from explaining the truth. Some
wrong forms can follow much of the truth's path whatever the method: a linear drift follows
3 a (1 - a) of a step at a fraction a of the recording (0.38-0.75 for a in 0.15-0.85), and a
temperature read through two thermal lags can take nearly any slow monotone shape. This module
measures that per trial, before any noise, so the scorer can tell a method's confusion from the
shapes' own overlap.

The *shape share* of a wrong form is the fraction of the injected change's energy (the raw
magnetometer with the effect minus the same draws without it, each axis's mean removed: the
calibration's hard iron takes a constant) that the form's best design fits by least squares:

    share = max over designs d of  1 - |P_d^perp s|^2 / |s - mean(s)|^2,

with P_d^perp the projection off the design's columns G_d (the form's own ``G``, an offset on each
axis) and three constants. Only the forms whose columns depend on time and the aux signals alone
are measured (SHAPE_FORMS): they need no calibration state, so the share is a property of the
trial, not of a fit.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

#: wrong forms whose design is an offset made of time and aux signals (drift, step, temperature,
#: current, throttle): their shape share is measured
SHAPE_FORMS = ("hard_iron_drift", "hard_iron_step", "temperature_offset", "current_hard_iron", "throttle_hard_iron")

#: a wrong form sharing at least this much of the truth's noise-free change is confusable with it
#: by shape: the line "closes at most 0.3" is not asked of it (the same 0.3 as the line itself)
SHAPE_CONFUSABLE = 0.3


def _env(t, aux):
    """The minimal diagnosis environment the SHAPE_FORMS read: the time base and aux columns."""
    frame = SimpleNamespace(t=np.asarray(t, float), aux={k: np.asarray(v, float) for k, v in aux.items()},
                            duration=float(t[-1] - t[0]))
    return SimpleNamespace(frame=frame, cache={})


def _share(columns, s):
    """Least-squares share of s (N, 3) on columns (N, 3, k) plus a constant per axis."""
    n, _, k = columns.shape
    A = np.zeros((3 * n, k + 3))
    A[:, :k] = columns.reshape(3 * n, k)                # row 3 i + j: sample i, axis j
    for j in range(3):
        A[j::3, k + j] = 1.0
    y = s.reshape(3 * n)
    total = float(np.sum((s - s.mean(axis=0)) ** 2))
    if not total > 0.0:
        return None
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    r = y - A @ coef
    return float(max(0.0, 1.0 - (r @ r) / total))


def shape_shares(t, aux, change, names=SHAPE_FORMS):
    """{form name: share} of the injected change (N, 3) for each form in ``names`` whose aux
    signals the recording has (a form missing a column is left out)."""
    from mkc_stream.diagnose.forms import FORMS

    change = np.asarray(change, float)
    if change.ndim != 2 or change.shape[1] != 3 or change.shape[0] != len(t) or not np.all(np.isfinite(change)):
        return {}
    env = _env(t, aux)
    out = {}
    for name in names:
        form = FORMS[name]
        best = None
        try:
            designs = form.designs(env)
            for d in designs:
                v = _share(np.asarray(form.G(env, d)(env.frame, None, None), float), change)
                if v is not None and (best is None or v > best):
                    best = v
        except KeyError:                                # an aux column the recording lacks
            continue
        if best is not None:
            out[name] = best
    return out
