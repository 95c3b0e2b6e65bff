"""Noise beyond white Gaussian: quantization and coloured (correlated) noise.

* quantization: the output is a multiple of lsb (0.01-1 uT: 16-bit parts at +-8 G are ~0.02 uT,
  12-bit parts ~0.3 uT); visible as a lattice in the raw values and, when lsb is comparable to
  the noise, in the residual distribution.
* colored_noise: a first-order Gauss-Markov process per axis (sigma 0.01-0.5 uT, correlation
  time tau 0.1-60 s): flicker and slow environmental fields that white noise does not have.

Diagnosis: both are estimated from the data and carried by the replicas. Quantization: the
baseline's lattice of raw values, per axis. Coloured noise: Gauss-Markov components fitted to the
residual's excess autocovariance and block variogram (:func:`.noise_fit.colored_fit`).
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext
from .form import EstimatedForm, ReplicaEffect
from .noise_fit import colored_fit, colored_refined


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


# -- diagnosis forms ---------------------------------------------------------------------------

def _quant_estimate(env, ctx, mult):
    lat = env.base.lattice
    if not np.nanmax(lat["strength"]) > 0.5:
        return None
    return {"q": lat["q"].tolist(), "phase": lat["phase"].tolist(), "lsb": float(np.nanmedian(lat["q"]))}


def _quant_replica(env, p):
    q, ph = np.asarray(p["q"]), np.asarray(p["phase"])

    def fn(ctx):
        ok = np.isfinite(q) & (q > 0)
        ctx.m[:, ok] = np.round((ctx.m[:, ok] - ph[ok]) / q[ok]) * q[ok] + ph[ok]
    return [(ReplicaEffect("quantization", "range", fn), {})]


def _quant_magnitude(env, p):
    val, unit = env.field_unit(p["lsb"])
    return {"value": val, "unit": unit, "meaning": "least significant bit"}


def _colored_replica(env, p):
    return [(COLORED_NOISE, {"sigma": s_, "tau": t_}) for s_, t_ in p["components"] if s_ > 0]


def _colored_magnitude(env, p):
    comps = p["components"]
    val, unit = env.field_unit(float(np.sqrt(sum(s_ ** 2 for s_, _ in comps))))
    return {"value": val, "unit": unit, "components": [list(c) for c in comps],
            "meaning": "standard deviation per axis (Gauss-Markov components: [sigma, tau s])"}


# -- the library's entries ------------------------------------------------------------------------

QUANTIZATION = Effect(
    name="quantization", family="noise", stage="range",
    params=(Param("lsb", "uT", 0.01, 1.0, 0.3, "output resolution"),
            Param("offset", "uT", -1.0, 1.0, 0.0, "lattice offset")),
    needs=(), forward=_quantization_forward, testable=_always,
    form=EstimatedForm("noise", _quant_estimate, _quant_replica, _quant_magnitude),
    doc="output rounded to a multiple of lsb")

COLORED_NOISE = Effect(
    name="colored_noise", family="noise", stage="noise",
    params=(Param("sigma", "uT", 0.01, 0.5, 0.1, "standard deviation per axis"),
            Param("tau", "s", 0.1, 60.0, 5.0, "correlation time")),
    needs=(), forward=_colored_forward, testable=_always,
    form=EstimatedForm("noise", colored_fit, _colored_replica, _colored_magnitude, refine=colored_refined),
    doc="first-order Gauss-Markov noise per axis")

EFFECTS = (QUANTIZATION, COLORED_NOISE)
