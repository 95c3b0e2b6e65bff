"""Hard iron that moves with time: a slow drift, a sudden step, a random walk.

Typical: drift 0.01-1 uT/h (magnetised parts relaxing, sensor offset ageing); a step of
0.1-5 uT when something magnetic is moved or a part is magnetised by a strong field; a random
walk of 0.05-2 uT/sqrt(h) (offset instability).

Diagnosis: drift and step are linear in their vectors (the step time by a grid search over the
recording's quantiles); the random walk is estimated from the blocks' apparent hard iron,
whose block-to-block wander grows with it, and carried by the replicas.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, vec
from .form import EstimatedForm, MeanForm, diag, single_design, vec_magnitude
from .noise_fit import _noise_samples, _variogram_excess, block_offsets


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


# -- diagnosis forms ---------------------------------------------------------------------------

def _drift_G(env, d):
    x = (env.frame.t - env.frame.t.mean()) / 3600.0
    return lambda frame, m, st: diag(x)


def _step_designs(env):
    t = env.frame.t
    qs = np.linspace(0.03, 0.97, 63)
    return [{"t_step": float(x)} for x in np.quantile(t, qs)]


def _step_G(env, d):
    x = (env.frame.t >= d["t_step"]).astype(float)
    x -= x.mean()
    return lambda frame, m, st: diag(x)


def _step_magnitude(env, d, th):
    out = vec_magnitude(env, th, 1.0, False, "")
    out["t_step_s"] = d["t_step"] - float(env.frame.t[0])
    return out


def _walk_stat(env, bs, mult):
    o = block_offsets(env, bs)
    tr = np.flatnonzero(mult > 0)
    pairs = [(a, b) for a, b in zip(tr[:-1], tr[1:]) if np.isfinite(o[a]).all() and np.isfinite(o[b]).all()]
    if not pairs:
        return np.nan, 0
    d = np.array([np.sum((o[b] - o[a]) ** 2) for a, b in pairs])
    gaps = np.array([b - a for a, b in pairs])
    return float(np.mean(d)), float(np.mean(gaps))


def _walk_neighbours(env, ctx, mult):
    """The walk from the mean squared change between neighbouring blocks' apparent hard iron,
    when it exceeds the replicas' by 3 of their sd; else None."""
    D, gap = _walk_stat(env, ctx.real_bs, mult)
    Dr = np.array([_walk_stat(env, bs, mult)[0] for bs in ctx.rep_bs])
    Dr = Dr[np.isfinite(Dr)]
    if not np.isfinite(D) or Dr.size < 3:
        return None
    ex = D - Dr.mean()
    if not ex > 3 * Dr.std(ddof=1):
        return None
    L = env.frame.duration / env.frame.n_blocks
    q2 = ex / (3.0 * (gap - 1.0 / 3.0) * L)           # per axis, unit^2/s (block means gap*L apart)
    return {"q": float(np.sqrt(q2) * 60.0)}           # unit/sqrt(h)


def walk_from_variogram(k, excess, sd, L):
    """q (unit/sqrt(h)) of a Wiener process fitted to the excess variogram of the blocks'
    apparent hard iron at block lags k, or None when its longest lag is within 3 replica sd.

    Means over blocks of length L of a Wiener process of intensity q^2 per axis, k blocks apart,
    differ by E|o_(i+k) - o_i|^2 = 3 q^2 L (k - 1/3) over the three axes; q^2 is the weighted
    least-squares slope through the origin (weights 1/sd^2)."""
    k, excess, sd = (np.asarray(x, float) for x in (k, excess, sd))
    if not (np.all(np.isfinite(excess)) and np.all(sd > 0) and excess[-1] > 3.0 * sd[-1]):
        return None
    x = 3.0 * L * (k - 1.0 / 3.0)
    w = 1.0 / sd ** 2
    q2 = float(np.sum(w * x * excess) / np.sum(w * x * x))
    return float(np.sqrt(q2) * 60.0) if q2 > 0 else None


def _walk_estimate(env, ctx, mult):
    """The neighbouring blocks first; a slow walk shows little there and grows with the lag, so
    when they do not see it, the variogram to 8 block lags the coloured-noise fit reads
    (decision 0032)."""
    est = _walk_neighbours(env, ctx, mult)
    if est is not None:
        return est
    vgm = _variogram_excess(env, _noise_samples(env, ctx), mult)
    if vgm is None:
        return None
    q = walk_from_variogram(*vgm, env.frame.duration / env.frame.n_blocks)
    return None if q is None else {"q": q}


def _walk_magnitude(env, p):
    val, unit = env.field_unit(p["q"])
    return {"value": val, "unit": unit + "/sqrt(h)"}


# -- the library's entries ------------------------------------------------------------------------

HARD_IRON_DRIFT = Effect(
    name="hard_iron_drift", family="drift", stage="offset",
    params=(Param("vx", "uT/h", 0.01, 1.0, 0.3), Param("vy", "uT/h", 0.01, 1.0, -0.2),
            Param("vz", "uT/h", 0.01, 1.0, 0.25)),
    needs=(), forward=_drift_forward, testable=_long_enough(60.0),
    form=MeanForm(single_design, _drift_G, 3, lambda env, d, th: vec_magnitude(env, th, 1.0, False, "/h")),
    doc="hard iron b + v (t - t_0)")

HARD_IRON_STEP = Effect(
    name="hard_iron_step", family="drift", stage="offset",
    params=(Param("dx", "uT", 0.1, 5.0, 0.8), Param("dy", "uT", 0.1, 5.0, -0.5),
            Param("dz", "uT", 0.1, 5.0, 0.6),
            Param("t_step", "s", 0.0, 1e9, -1.0, "time of the step (negative: mid-recording)")),
    needs=(), forward=_step_forward, testable=_long_enough(10.0),
    form=MeanForm(_step_designs, _step_G, 3, _step_magnitude),
    doc="hard iron b + delta [t >= t_step]")

BIAS_RANDOM_WALK = Effect(
    name="bias_random_walk", family="drift", stage="noise",
    params=(Param("q", "uT/sqrt(h)", 0.05, 2.0, 0.5, "random-walk intensity per axis"),),
    needs=(), forward=_walk_forward, testable=_long_enough(60.0),
    form=EstimatedForm("noise", _walk_estimate, lambda env, p: [(BIAS_RANDOM_WALK, {"q": p["q"]})], _walk_magnitude),
    doc="hard iron b + W(t), W a Wiener process per axis")

EFFECTS = (HARD_IRON_DRIFT, HARD_IRON_STEP, BIAS_RANDOM_WALK)
