"""Fields of the platform's own currents: wires and motors near the magnetometer.

A current I in a wire adds a field proportional to I at the sensor (Biot-Savart is linear in
I), so the hard iron becomes b + k I; typical k is 0.005-0.5 uT/A. Motor magnets and ESC
switching add a field that grows with the motor command; the library models it as
k * throttle^p with k the offset at full throttle.

Diagnosis: the current form is linear in k; the throttle form fits p throttle + q throttle^2 per
axis (means removed) and reports p + q, the offset at full throttle.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, aux_or_raise, span_ok, vec
from .form import MeanForm, diag, single_design, vec_magnitude


def _current_forward(ctx: SimContext, kx, ky, kz):
    current = aux_or_raise(ctx, "current", "current_hard_iron")
    ctx.m += np.outer(current, vec(kx, ky, kz))


def _throttle_forward(ctx: SimContext, kx, ky, kz, exponent):
    thr = np.clip(aux_or_raise(ctx, "throttle", "throttle_hard_iron"), 0.0, None)
    ctx.m += np.outer(thr ** exponent, vec(kx, ky, kz))


def _current_G(env, d):
    x = env.frame.aux["current"] - env.frame.aux["current"].mean()
    return lambda frame, m, st: diag(x)


def _throttle_G(env, d):
    x = env.frame.aux["throttle"]
    a, b = x - x.mean(), x * x - (x * x).mean()
    return lambda frame, m, st: np.concatenate([diag(a), diag(b)], axis=2)


def _throttle_magnitude(env, d, th):
    out = vec_magnitude(env, np.asarray(th[:3]) + np.asarray(th[3:]), 1.0, False, "")
    out["meaning"] = "offset at full throttle against zero throttle"
    return out


CURRENT_HARD_IRON = Effect(
    name="current_hard_iron", family="electrical", stage="offset",
    params=(Param("kx", "uT/A", 0.005, 0.5, 0.05), Param("ky", "uT/A", 0.005, 0.5, -0.03),
            Param("kz", "uT/A", 0.005, 0.5, 0.04)),
    needs=("current",), forward=_current_forward,
    testable=lambda ev: span_ok(ev, "current", 0.5, "A"),
    form=MeanForm(single_design, _current_G, 3, lambda env, d, th: vec_magnitude(env, th, 1.0, False, "/A")),
    doc="hard iron b + k I (I the current column, A)")

THROTTLE_HARD_IRON = Effect(
    name="throttle_hard_iron", family="electrical", stage="offset",
    params=(Param("kx", "uT", 0.1, 10.0, 1.0, "offset at full throttle, x"),
            Param("ky", "uT", 0.1, 10.0, 0.5), Param("kz", "uT", 0.1, 10.0, -0.8),
            Param("exponent", "1", 1.0, 2.0, 1.5, "shape of the throttle law")),
    needs=("throttle",), forward=_throttle_forward,
    testable=lambda ev: span_ok(ev, "throttle", 0.1, ""),
    form=MeanForm(single_design, _throttle_G, 6, _throttle_magnitude),
    doc="hard iron b + k throttle^exponent")

EFFECTS = (CURRENT_HARD_IRON, THROTTLE_HARD_IRON)
