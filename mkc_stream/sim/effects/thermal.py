"""Temperature effects: an offset that follows temperature and a gain that follows it.

Both act through the sensor die temperature, which lags the measured (board) temperature by a
first-order thermal time constant ``tau``. Typical magnitudes: offset tempco 1-50 nT/degC
(AMR/fluxgate parts and the PCB's own magnetised parts), gain tempco 0.005-0.3 %/degC.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, aux_or_raise, first_order_lag, span_ok, vec


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


_TAU = Param("tau", "s", 0.0, 600.0, 30.0, "thermal lag of the die behind the temp column")
_TREF = Param("t_ref", "degC", -40.0, 85.0, 25.0, "temperature of zero effect")

TEMPERATURE_OFFSET = Effect(
    name="temperature_offset", family="thermal", stage="offset", kind="mean",
    params=(Param("cx", "nT/degC", 1.0, 50.0, 12.0, "offset tempco, x (|c| typically 1-50)"),
            Param("cy", "nT/degC", 1.0, 50.0, -6.0, "offset tempco, y"),
            Param("cz", "nT/degC", 1.0, 50.0, 15.0, "offset tempco, z"),
            _TAU, _TREF),
    needs=("temp",), forward=_offset_forward, testable=_needs_temp,
    doc="hard-iron offset c (T_die - t_ref), T_die = temp lagged by tau")

TEMPERATURE_SCALE = Effect(
    name="temperature_scale", family="thermal", stage="sensor", kind="mean",
    params=(Param("ax", "%/degC", 0.005, 0.3, 0.05, "gain tempco, x"),
            Param("ay", "%/degC", 0.005, 0.3, 0.03, "gain tempco, y"),
            Param("az", "%/degC", 0.005, 0.3, 0.04, "gain tempco, z"),
            _TAU, _TREF),
    needs=("temp",), forward=_scale_forward, testable=_needs_temp,
    doc="per-axis gain (1 + alpha (T_die - t_ref)) on the field seen after the hard iron")

EFFECTS = (TEMPERATURE_OFFSET, TEMPERATURE_SCALE)
