"""Departures from the linear sensor and the linear (soft + hard) iron model.

* scale_nonlinearity: each axis bends cubically, (m_j - b_j) -> (m_j - b_j) + beta_j ((m_j - b_j)/50 uT)^3;
  beta is the departure at 50 uT, typically 10-500 nT (AMR and Hall parts near full scale).
* saturation: the output clips at +-limit (the ADC or the sensor range); 30-5000 uT.
* higher_order_soft_iron: the platform iron's magnetisation has a second-order term in the
  field, dm = Q(B, B) / 50 uT; q is its RMS over all directions at 50 uT (0.05-1 uT).
* hysteresis: magnetisation lags the field; the library's form is -h tanh(dm_j/dt / rate)
  per axis, h the half-width of the loop (0.02-0.5 uT).
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, coverage_ok, vec

F_REF = 50.0   # uT: the field at which nonlinearity magnitudes are quoted


def _nonlin_forward(ctx: SimContext, bx, by, bz):
    beta = vec(bx, by, bz) * 1e-3
    ctx.m += beta * ((ctx.m - ctx.b) / F_REF) ** 3


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


def _hysteresis_forward(ctx: SimContext, width, rate):
    rel = ctx.m - ctx.b
    dmdt = np.gradient(rel, ctx.t, axis=0) if ctx.n > 2 else np.zeros_like(rel)
    ctx.m += -width * np.tanh(dmdt / max(rate, 1e-9))


def _always(ev):
    return (True, "needs no aux signal") if ev.n >= 500 else (False, f"only {ev.n} samples")


SCALE_NONLINEARITY = Effect(
    name="scale_nonlinearity", family="nonlinear", stage="sensor", kind="mean",
    params=(Param("bx", "nT", 10.0, 500.0, 150.0, "departure at 50 uT, x"),
            Param("by", "nT", 10.0, 500.0, -100.0), Param("bz", "nT", 10.0, 500.0, 120.0)),
    needs=(), forward=_nonlin_forward, testable=lambda ev: coverage_ok(ev, 0.5),
    doc="per-axis cubic gain error")

SATURATION = Effect(
    name="saturation", family="nonlinear", stage="range", kind="mask",
    params=(Param("limit", "uT", 30.0, 5000.0, 60.0, "output range +-limit"),),
    needs=(), forward=_saturation_forward, testable=_always,
    doc="output clipped at +-limit")

HIGHER_ORDER_SOFT_IRON = Effect(
    name="higher_order_soft_iron", family="nonlinear", stage="offset", kind="mean",
    params=(Param("q", "uT", 0.05, 1.0, 0.3, "RMS of the quadratic term at 50 uT"),
            Param("pattern", "seed", 0, 1e6, 1, "which quadratic form")),
    needs=(), forward=_higher_order_forward, testable=lambda ev: coverage_ok(ev, 0.5),
    doc="dm = q Q(B, B) / (50 uT)^2")

HYSTERESIS = Effect(
    name="hysteresis", family="nonlinear", stage="sensor", kind="mean",
    params=(Param("width", "uT", 0.02, 0.5, 0.15, "half-width of the loop"),
            Param("rate", "uT/s", 0.5, 50.0, 5.0, "field rate at which the loop is fully open")),
    needs=(), forward=_hysteresis_forward,
    testable=lambda ev: coverage_ok(ev, 0.3),
    doc="-width tanh(dm/dt / rate) per axis")

EFFECTS = (SCALE_NONLINEARITY, SATURATION, HIGHER_ORDER_SOFT_IRON, HYSTERESIS)
