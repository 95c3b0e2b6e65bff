"""Hard iron that moves with time: a slow drift, a sudden step, a random walk.

Typical: drift 0.01-1 uT/h (magnetised parts relaxing, sensor offset ageing); a step of
0.1-5 uT when something magnetic is moved or a part is magnetised by a strong field; a random
walk of 0.05-2 uT/sqrt(h) (offset instability).
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, vec


def _drift_forward(ctx: SimContext, vx, vy, vz):
    ctx.m += np.outer((ctx.t - ctx.t[0]) / 3600.0, vec(vx, vy, vz))


def _step_forward(ctx: SimContext, dx, dy, dz, t_step):
    t0 = ctx.t[0] + 0.5 * (ctx.t[-1] - ctx.t[0]) if not np.isfinite(t_step) or t_step < 0 else t_step
    ctx.m += np.outer((ctx.t >= t0).astype(np.float64), vec(dx, dy, dz))
    ctx.truth["t_step"] = float(t0)


def _walk_forward(ctx: SimContext, q):
    dt = np.diff(ctx.t, prepend=ctx.t[0])
    steps = ctx.rng.normal(size=(ctx.n, 3)) * np.sqrt(np.maximum(dt, 0.0))[:, None]
    ctx.m += (q / 60.0) * np.cumsum(steps, axis=0)          # uT/sqrt(h) -> uT/sqrt(s)


def _long_enough(minimum_s):
    def test(ev):
        if ev.duration < minimum_s:
            return False, f"the recording lasts {ev.duration:.0f} s (needs >= {minimum_s:.0f} s)"
        return True, f"the recording lasts {ev.duration:.0f} s"
    return test


HARD_IRON_DRIFT = Effect(
    name="hard_iron_drift", family="drift", stage="offset", kind="mean",
    params=(Param("vx", "uT/h", 0.01, 1.0, 0.3), Param("vy", "uT/h", 0.01, 1.0, -0.2),
            Param("vz", "uT/h", 0.01, 1.0, 0.25)),
    needs=(), forward=_drift_forward, testable=_long_enough(60.0),
    doc="hard iron b + v (t - t_0)")

HARD_IRON_STEP = Effect(
    name="hard_iron_step", family="drift", stage="offset", kind="mean",
    params=(Param("dx", "uT", 0.1, 5.0, 0.8), Param("dy", "uT", 0.1, 5.0, -0.5),
            Param("dz", "uT", 0.1, 5.0, 0.6),
            Param("t_step", "s", 0.0, 1e9, -1.0, "time of the step (negative: mid-recording)")),
    needs=(), forward=_step_forward, testable=_long_enough(10.0),
    doc="hard iron b + delta [t >= t_step]")

BIAS_RANDOM_WALK = Effect(
    name="bias_random_walk", family="drift", stage="noise", kind="noise",
    params=(Param("q", "uT/sqrt(h)", 0.05, 2.0, 0.5, "random-walk intensity per axis"),),
    needs=(), forward=_walk_forward, testable=_long_enough(60.0),
    doc="hard iron b + W(t), W a Wiener process per axis")

EFFECTS = (HARD_IRON_DRIFT, HARD_IRON_STEP, BIAS_RANDOM_WALK)
