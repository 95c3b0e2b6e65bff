"""Temperature effects: an offset that follows temperature and a gain that follows it.

Both act through the sensor die temperature, which lags the measured (board) temperature by a
first-order thermal time constant ``tau``. Typical magnitudes: offset tempco 1-50 nT/degC
(AMR/fluxgate parts and the PCB's own magnetised parts), gain tempco 0.005-0.3 %/degC.

Diagnosis: both are linear in their coefficients once the lag is fixed; the forms try the die
temperature through two lag stages on a grid of lags.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, aux_or_raise, first_order_lag, span_ok, vec
from .form import MeanForm, diag, vec_magnitude


def _die_temperature(ctx: SimContext, tau: float, name: str) -> np.ndarray:
    return first_order_lag(ctx.t, aux_or_raise(ctx, "temp", name), tau)


def _offset_forward(ctx: SimContext, cx, cy, cz, tau, t_ref):
    T = _die_temperature(ctx, tau, "temperature_offset")
    c = vec(cx, cy, cz) * 1e-3                      # nT/degC -> uT/degC
    ctx.m += np.outer(T - t_ref, c)


def _scale_forward(ctx: SimContext, ax, ay, az, tau, t_ref):
    T = _die_temperature(ctx, tau, "temperature_scale")
    alpha = vec(ax, ay, az) * 1e-2                  # %/degC -> 1/degC
    ctx.m += (ctx.m - ctx.b) * np.outer(T - t_ref, alpha)


def _needs_temp(ev):
    return span_ok(ev, "temp", 2.0, "degC")


# -- diagnosis forms ---------------------------------------------------------------------------

def _tau_grid(env):
    """Thermal lags tried (s): doubling steps, up to the length of the recording."""
    return [tau for tau in (0.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0) if tau <= env.frame.duration]


def _tau_pairs(env):
    """The die temperature as the temp column through two first-order thermal stages (board,
    then die; tau_a <= tau_b, 0 = no stage). The forward model has one stage; the second lets
    one form follow a die that sits further from the temperature sensor."""
    g = _tau_grid(env)
    return [{"tau": a, "tau2": b} for i, a in enumerate(g) for b in g[i:] if b > 0 or a == 0]


def _die(env, d):
    """Die temperature of a design (temp through its two lag stages), mean removed, degC."""
    key = ("die", d["tau"], d["tau2"])
    if key not in env.cache:
        x = first_order_lag(env.frame.t, first_order_lag(env.frame.t, env.frame.aux["temp"], d["tau"]), d["tau2"])
        env.cache[key] = x - x.mean()
    return env.cache[key]


def _offset_G(env, d):
    x = _die(env, d)
    return lambda frame, m, st: diag(x)


def _offset_magnitude(env, d, th):
    out = vec_magnitude(env, th, 1.0, True, "/degC")
    out.update(tau_s=[d["tau"], d["tau2"]], meaning="offset per degC of die temperature (two lag stages)")
    return out


def _scale_G(env, d):
    x = _die(env, d)
    return lambda frame, m, st: diag((m - st.b) * x[:, None])


def _scale_magnitude(env, d, th):
    a = np.asarray(th) * 100.0
    return {"value": float(np.linalg.norm(a)), "unit": "%/degC", "vector": a.tolist(),
            "tau_s": [d["tau"], d["tau2"]]}


# -- the library's entries ------------------------------------------------------------------------

_TAU = Param("tau", "s", 0.0, 600.0, 30.0, "thermal lag of the die behind the temp column")
_TREF = Param("t_ref", "degC", -40.0, 85.0, 25.0, "temperature of zero effect")

TEMPERATURE_OFFSET = Effect(
    name="temperature_offset", family="thermal", stage="offset",
    params=(Param("cx", "nT/degC", 1.0, 50.0, 12.0, "offset tempco, x (|c| typically 1-50)"),
            Param("cy", "nT/degC", 1.0, 50.0, -6.0, "offset tempco, y"),
            Param("cz", "nT/degC", 1.0, 50.0, 15.0, "offset tempco, z"),
            _TAU, _TREF),
    needs=("temp",), forward=_offset_forward, testable=_needs_temp,
    form=MeanForm(_tau_pairs, _offset_G, 3, _offset_magnitude),
    doc="hard-iron offset c (T_die - t_ref), T_die = temp lagged by tau")

TEMPERATURE_SCALE = Effect(
    name="temperature_scale", family="thermal", stage="sensor",
    params=(Param("ax", "%/degC", 0.005, 0.3, 0.05, "gain tempco, x"),
            Param("ay", "%/degC", 0.005, 0.3, 0.03, "gain tempco, y"),
            Param("az", "%/degC", 0.005, 0.3, 0.04, "gain tempco, z"),
            _TAU, _TREF),
    needs=("temp",), forward=_scale_forward, testable=_needs_temp,
    form=MeanForm(_tau_pairs, _scale_G, 3, _scale_magnitude),
    doc="per-axis gain (1 + alpha (T_die - t_ref)) on the field seen after the hard iron")

EFFECTS = (TEMPERATURE_OFFSET, TEMPERATURE_SCALE)
