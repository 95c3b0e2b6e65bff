"""Noise beyond white Gaussian: quantization and coloured (correlated) noise.

* quantization: the output is a multiple of lsb (0.01-1 uT: 16-bit parts at +-8 G are ~0.02 uT,
  12-bit parts ~0.3 uT); visible as a lattice in the raw values and, when lsb is comparable to
  the noise, in the residual distribution.
* colored_noise: a first-order Gauss-Markov process per axis (sigma 0.01-0.5 uT, correlation
  time tau 0.1-60 s): flicker and slow environmental fields that white noise does not have.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext


def _quantization_forward(ctx: SimContext, lsb, offset):
    if lsb > 0:
        ctx.m[:] = np.round((ctx.m - offset) / lsb) * lsb + offset


def gauss_markov(rng, t: np.ndarray, sigma: float, tau: float, dims: int = 3) -> np.ndarray:
    """Stationary first-order Gauss-Markov process (N, dims) sampled at t (exact for any dt)."""
    from .gm import gm_filter

    dt = np.diff(t, prepend=t[0])
    phi = np.exp(-np.maximum(dt, 0.0) / max(tau, 1e-9))
    w = rng.normal(size=(t.shape[0], dims))
    return sigma * gm_filter(phi, w)


def _colored_forward(ctx: SimContext, sigma, tau):
    ctx.m += gauss_markov(ctx.rng, ctx.t, sigma, tau)


def _always(ev):
    return (True, "needs no aux signal") if ev.n >= 500 else (False, f"only {ev.n} samples")


QUANTIZATION = Effect(
    name="quantization", family="noise", stage="range", kind="noise",
    params=(Param("lsb", "uT", 0.01, 1.0, 0.3, "output resolution"),
            Param("offset", "uT", -1.0, 1.0, 0.0, "lattice offset")),
    needs=(), forward=_quantization_forward, testable=_always,
    doc="output rounded to a multiple of lsb")

COLORED_NOISE = Effect(
    name="colored_noise", family="noise", stage="noise", kind="noise",
    params=(Param("sigma", "uT", 0.01, 0.5, 0.1, "standard deviation per axis"),
            Param("tau", "s", 0.1, 60.0, 5.0, "correlation time")),
    needs=(), forward=_colored_forward, testable=_always,
    doc="first-order Gauss-Markov noise per axis")

EFFECTS = (QUANTIZATION, COLORED_NOISE)
