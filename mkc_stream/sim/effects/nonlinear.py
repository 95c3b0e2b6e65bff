"""Departures from the linear sensor and the linear (soft + hard) iron model.

* scale_nonlinearity: each axis bends cubically, (m_j - b_j) -> (m_j - b_j) + beta_j ((m_j - b_j)/50 uT)^3;
  beta is the departure at 50 uT, typically 10-500 nT (AMR and Hall parts near full scale).
* sensor_compression: each axis compresses smoothly towards its range, about the sensor's own
  zero, m_j -> m_j - d_j (m_j / 50 uT)^3 with d the departure at 50 uT (0.2-5 uT: a sensor
  driven near saturation). The sensor's zero is not the hard-iron centre: with x = m - b,
  (x + b)^3 = x^3 + 3 b x^2 + 3 b^2 x + b^3, so it leaves an even (quadratic) term per axis
  beside the odd (cubic) one (the linear part is absorbed by the calibration).
* saturation: the output clips at +-limit (the ADC or the sensor range); 30-5000 uT.
* higher_order_soft_iron: the platform iron's magnetisation has a second-order term in the
  field, dm = Q(B, B) / 50 uT; q is its RMS over all directions at 50 uT (0.05-1 uT).
* hysteresis: the magnetisation lags the field by a loop whose width does not depend on how
  fast the field moves (ferromagnetic hysteresis at the rates a sensor turns); per axis a play
  operator of half-width h (0.02-0.5 uT): the reading trails a rising axis by h and a falling one
  by -h, and turns over once the axis has travelled 2 h back.

Diagnosis: the cubic gain, the per-axis cubic and quadratic terms of a compression, the quadratic soft iron (as the five degree-2 harmonics of the field
direction per axis) and the hysteresis (on a grid of loop widths) are linear in their coefficients;
saturation is found as pile-ups at the extremes of each axis, whose samples are then left out.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, coverage_ok, vec
from .form import EstimatedForm, MeanForm, ReplicaEffect, diag, single_design, vec_magnitude
from .play import play_operator

F_REF = 50.0   # uT: the field at which nonlinearity magnitudes are quoted


def _nonlin_forward(ctx: SimContext, bx, by, bz):
    beta = vec(bx, by, bz) * 1e-3
    ctx.m += beta * ((ctx.m - ctx.b) / F_REF) ** 3


def _compression_forward(ctx: SimContext, dx, dy, dz):
    d = vec(dx, dy, dz)
    ctx.m -= d * (ctx.m / F_REF) ** 3


def _saturation_forward(ctx: SimContext, limit):
    np.clip(ctx.m, -limit, limit, out=ctx.m)


def quadratic_pattern(seed: int) -> np.ndarray:
    """Q (3, 3, 3), symmetric and traceless in its last two indices, RMS of Q(u, u) = 1 on the sphere."""
    rng = np.random.default_rng(int(seed))
    Q = rng.normal(size=(3, 3, 3))
    Q = 0.5 * (Q + Q.transpose(0, 2, 1))
    Q -= np.einsum("jkk->j", Q)[:, None, None] * np.eye(3) / 3.0
    u = fibonacci_sphere(2000)
    dm = np.einsum("jkl,nk,nl->nj", Q, u, u)
    return Q / np.sqrt(np.mean(np.sum(dm * dm, axis=1)))


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _higher_order_forward(ctx: SimContext, q, pattern):
    Q = quadratic_pattern(int(pattern))
    ctx.m += q * np.einsum("jkl,nk,nl->nj", Q, ctx.B, ctx.B) / F_REF ** 2


def _hysteresis_forward(ctx: SimContext, width):
    ctx.m[:] = play_operator(np.ascontiguousarray(ctx.m, dtype=np.float64), float(width))


def _always(ev):
    return (True, "needs no aux signal") if ev.n >= 500 else (False, f"only {ev.n} samples")


# -- diagnosis forms ---------------------------------------------------------------------------

def _nonlin_G(env, d):
    return lambda frame, m, st: diag(((m - st.b) / env.F_ref) ** 3)


def _nonlin_magnitude(env, d, th):
    out = vec_magnitude(env, th, 1.0, True, "")
    out["meaning"] = "departure at 50 uT per axis" if env.to_uT else "departure at the fitted field"
    return out


def _compression_G(env, d):
    """Per axis, the odd and the even term about the hard-iron centre, each its departure at
    50 uT: dm_j = a_j (x_j / F)^3 + c_j (x_j / F)^2, x = m - b; theta = (a_x, a_y, a_z, c_x, c_y, c_z)."""
    def g(frame, m, st):
        x = (m - st.b) / env.F_ref
        return np.concatenate([diag(x ** 3), diag(x ** 2)], axis=2)
    return g


def _compression_magnitude(env, d, th):
    th = np.asarray(th, dtype=float)
    out = vec_magnitude(env, th, 1.0, False, "")
    # a compression about a point z below the centre, -d (x + z)^3, has cubic -d and quadratic
    # -3 d z / F: z_j = F c_j / (3 a_j) (the raw hard iron when that point is the raw zero)
    z = [float(env.F_ref * c / (3.0 * a)) if abs(a) > 1e-12 else None for a, c in zip(th[:3], th[3:])]
    out.update(cubic=out["vector"][:3], quadratic=out["vector"][3:],
               centre_from_zero=[None if v is None else env.field_unit(v)[0] for v in z],
               meaning=("per-axis cubic and quadratic departures at 50 uT about the hard-iron centre; "
                        "centre_from_zero: that centre measured from the point the compression is about"
                        if env.to_uT else "per-axis cubic and quadratic departures at the fitted field"))
    return out


def _quad_basis(v):
    """The five real degree-2 spherical harmonics of unit vectors v (N, 3), unit RMS on the sphere."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.sqrt(15) * x * y, np.sqrt(15) * x * z, np.sqrt(15) * y * z,
                     np.sqrt(15 / 4) * (x * x - y * y), np.sqrt(5 / 4) * (x * x + y * y - 2 * z * z)], axis=1)


def norm_pattern_rms(dm_of_u) -> float:
    """RMS over directions of u . dm(u) after removing what a hard iron absorbs (degree 0 and 1):
    the observable size of a direction-dependent raw error (a quadratic raw error has null
    directions the norm cannot see, so its raw-frame size is not identifiable)."""
    u = fibonacci_sphere(2000)
    r = np.sum(u * dm_of_u(u), axis=1)
    A = np.column_stack([np.ones(len(u)), u])
    r = r - A @ np.linalg.lstsq(A, r, rcond=None)[0]
    return float(np.sqrt(np.mean(r * r)))


def _higher_order_G(env, d):
    def g(frame, m, st):
        mc = (m - st.b) @ st.S.T
        Y = _quad_basis(mc / np.linalg.norm(mc, axis=1, keepdims=True))
        out = np.zeros((m.shape[0], 3, 15))
        for j in range(3):
            out[:, j, 5 * j:5 * j + 5] = Y
        return out
    return g


def _higher_order_magnitude(env, d, th):
    F = float(env.base.fit.state.F)
    val, unit = env.field_unit(norm_pattern_rms(lambda u: np.stack([_quad_basis(u) @ np.asarray(th)[5 * j:5 * j + 5]
                                                                    for j in range(3)], axis=1))
                               * (env.F_ref / F) ** 2)
    return {"value": val, "unit": unit,
            "meaning": ("RMS over directions of the field-strength error no ellipsoid can fit, at 50 uT"
                        if env.to_uT else "RMS over directions of the field-strength error no ellipsoid can fit")}


#: loop half-widths tried, as fractions of the fitted field (0.05-0.4 uT at 50 uT)
HYSTERESIS_WIDTHS = (0.001, 0.002, 0.004, 0.008)
#: samples averaged (this one and the ones before) into the play's input: white noise of the
#: loop's own size would otherwise reverse it at every sample (on 13 of the blind benchmark's
#: play-operator loops the best width's column follows 0.91-0.98 of the injected change at 3
#: samples, 0.64-0.94 at 1; decision 0034)
HYSTERESIS_SMOOTHING = 3


def _window_mean(x, before, after, skip_centre):
    """Mean of x over samples k - before .. k + after (those that exist), without x_k when
    skip_centre."""
    n = x.shape[0]
    c = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    k = np.arange(n)
    lo, hi = np.maximum(k - before, 0), np.minimum(k + after, n - 1)
    total, count = c[hi + 1] - c[lo], (hi - lo + 1).astype(float)
    if skip_centre:
        total, count = total - x, count - 1.0
    return total / np.maximum(count, 1.0)[:, None]


def loop_column(m, width):
    """The hysteresis form's column per axis, in [-1, 1]: -1 while the axis rises, +1 while it
    falls, turning over as it travels 2 width after a reversal, at any rate.

    The loop's state before sample k is a play operator of half-width ``width``
    (:func:`.play.play_operator`) run over the causal mean of HYSTERESIS_SMOOTHING samples, up
    to sample k - 1; at k it is clipped to within ``width`` of the mean of the neighbours
    k - 2 .. k + 2 without k: column_k = (clip(y_{k-1}, x_k - w, x_k + w) - x_k) / w. The column
    at k does not read m_k: one that did would share the noise of the residual it is regressed
    on, and the matched test would fire on noise (decision 0034). A play commutes with a
    constant shift, so raw values do as well as calibrated ones."""
    m = np.ascontiguousarray(m, dtype=np.float64)
    y = play_operator(_window_mean(m, HYSTERESIS_SMOOTHING - 1, 0, False), float(width))
    x = _window_mean(m, 2, 2, True)
    before = np.vstack([x[:1], y[:-1]])                  # no state before the first sample: column 0
    return (np.clip(before, x - width, x + width) - x) / width


def _hysteresis_designs(env):
    return [{"w": w} for w in HYSTERESIS_WIDTHS]


def _hysteresis_G(env, d):
    """Per axis, :func:`loop_column` of the raw magnetometer at half-width w = d["w"] F; its
    coefficient is the loop's half-width. The design {"k": inf} is the limit: a lag in
    proportion to dm/dt."""
    if np.isinf(d.get("k", 0.0)):
        md = env.mdot()
        x = -md / np.maximum(np.median(np.abs(md), axis=0), 1e-12)
        return lambda frame, m, st: diag(x)
    key = ("hysteresis_loop", d["w"])
    if key not in env.cache:
        env.cache[key] = loop_column(env.frame.m, d["w"] * float(env.base.fit.state.F))
    x = env.cache[key]
    return lambda frame, m, st: diag(x)


def _hysteresis_limit(env):
    """A loop's width does not depend on how fast the field moves (the play designs); a "loop"
    that grows in proportion to the rate, dm_j = -tau_j dm_j/dt, is a lag: a latency or an
    output filter, which other effects model."""
    return {"k": np.inf}, ("the lag grows in proportion to the field's rate (chi-square {excess:.0f} lower "
                           "than with the best loop width): a latency or output filter, not a hysteresis loop")


def _hysteresis_magnitude(env, d, th):
    val, unit = env.field_unit(float(np.sqrt(np.mean(np.square(th)))))
    return {"value": val, "unit": unit, "vector": [env.field_unit(x)[0] for x in th], "meaning": "loop half-width"}


def _sat_tol(env):
    q = np.nan_to_num(env.base.lattice["q"], nan=0.0) * (env.base.lattice["strength"] > 0.5)
    return np.maximum(0.5 * env.base.sigma_axis, 0.51 * q)


def _sat_estimate(env, ctx, mult):
    m = env.frame.m[np.isin(env.frame.block, np.flatnonzero(mult > 0))]
    tol = _sat_tol(env)
    levels = []
    for j in range(3):
        for sign in (1.0, -1.0):
            x = sign * m[:, j]
            top = x.max()
            n_at = int(np.sum(x >= top - tol[j]))
            n_band = int(np.sum((x < top - tol[j]) & (x >= top - 4 * tol[j])))
            if n_at >= max(8, 0.002 * m.shape[0]) and n_at > 2 * n_band:
                levels.append((j, sign, float(sign * top)))
    if not levels:
        return None
    return {"levels": levels, "limit": float(np.median([abs(L) for _, _, L in levels]))}


def _sat_replica(env, p):
    def fn(ctx):
        for j, sign, L in p["levels"]:
            if sign > 0:
                np.minimum(ctx.m[:, j], L, out=ctx.m[:, j])
            else:
                np.maximum(ctx.m[:, j], L, out=ctx.m[:, j])
    return [(ReplicaEffect("saturation", "range", fn), {})]


def _sat_mask(env, p, raw):
    tol = _sat_tol(env)
    ok = np.ones(raw.shape[0], dtype=bool)
    for j, sign, L in p["levels"]:
        ok &= ~(np.abs(raw[:, j] - L) <= tol[j])
    return ok


def _sat_magnitude(env, p):
    val, unit = env.field_unit(p["limit"])
    return {"value": val, "unit": unit, "levels": [[j, s, env.field_unit(L)[0]] for j, s, L in p["levels"]]}


# -- the library's entries ------------------------------------------------------------------------

SCALE_NONLINEARITY = Effect(
    name="scale_nonlinearity", family="nonlinear", stage="sensor",
    params=(Param("bx", "nT", 10.0, 500.0, 150.0, "departure at 50 uT, x"),
            Param("by", "nT", 10.0, 500.0, -100.0), Param("bz", "nT", 10.0, 500.0, 120.0)),
    needs=(), forward=_nonlin_forward, testable=lambda ev: coverage_ok(ev, 0.5),
    form=MeanForm(single_design, _nonlin_G, 3, _nonlin_magnitude),
    doc="per-axis cubic gain error")

SENSOR_COMPRESSION = Effect(
    name="sensor_compression", family="nonlinear", stage="sensor",
    params=(Param("dx", "uT", 0.2, 5.0, 3.0, "compression at 50 uT, x"),
            Param("dy", "uT", 0.2, 5.0, 3.0), Param("dz", "uT", 0.2, 5.0, 3.0)),
    needs=(), forward=_compression_forward, testable=lambda ev: coverage_ok(ev, 0.5),
    form=MeanForm(single_design, _compression_G, 6, _compression_magnitude, contains=("scale_nonlinearity",)),
    doc="m -> m - d (m / 50 uT)^3 per axis about the sensor's zero (odd and even terms about the centre)")

SATURATION = Effect(
    name="saturation", family="nonlinear", stage="range",
    params=(Param("limit", "uT", 30.0, 5000.0, 60.0, "output range +-limit"),),
    needs=(), forward=_saturation_forward, testable=_always,
    form=EstimatedForm("mask", _sat_estimate, _sat_replica, _sat_magnitude, mask=_sat_mask),
    doc="output clipped at +-limit")

HIGHER_ORDER_SOFT_IRON = Effect(
    name="higher_order_soft_iron", family="nonlinear", stage="offset",
    params=(Param("q", "uT", 0.05, 1.0, 0.3, "RMS of the quadratic term at 50 uT"),
            Param("pattern", "seed", 0, 1e6, 1, "which quadratic form")),
    needs=(), forward=_higher_order_forward, testable=lambda ev: coverage_ok(ev, 0.5),
    form=MeanForm(single_design, _higher_order_G, 15, _higher_order_magnitude),
    doc="dm = q Q(B, B) / (50 uT)^2")

HYSTERESIS = Effect(
    name="hysteresis", family="nonlinear", stage="sensor",
    params=(Param("width", "uT", 0.02, 0.5, 0.15, "half-width of the loop"),),
    needs=(), forward=_hysteresis_forward,
    testable=lambda ev: coverage_ok(ev, 0.3),
    form=MeanForm(_hysteresis_designs, _hysteresis_G, 3, _hysteresis_magnitude, limit=_hysteresis_limit),
    doc="per axis, a play operator of half-width width (a rate-independent loop)")

EFFECTS = (SCALE_NONLINEARITY, SENSOR_COMPRESSION, SATURATION, HIGHER_ORDER_SOFT_IRON, HYSTERESIS)
