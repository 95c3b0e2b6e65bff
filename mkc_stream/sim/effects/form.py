"""The diagnosis form an effect declares beside its forward model: how the diagnoser fits it.

Mean effects (a deterministic change of the raw signal) are linear in their parameters once
the nonlinear settings are fixed: dm = G(t) theta. G comes from the forward model's
derivative with respect to its parameters (e.g. temperature_offset: I_3 (T_lag(t) - mean);
temperature_scale: diag(m - b) (T_lag - mean); hard_iron_step: I_3 [t >= t0]); settings that
are not linear (thermal lag tau, step time t0, hysteresis loop width) are found by a grid search on
training blocks. Each design returns its G as a function of (frame, m, state) so that the
Gauss-Newton fit can re-evaluate it at the current hard iron.

Stochastic and clock effects are estimated from the data (autocovariance excess over the
replicas for coloured noise, block-to-block hard-iron wander for a random walk, the lattice of
raw values, pile-ups at the extremes, the statistics of time steps) and then *added to the
replicas*, which is how a simulator would carry them.

Every form function takes ``env``, the recording being diagnosed, which the diagnoser builds
(:class:`mkc_stream.diagnose.forms.Env`). What a form may read from it: ``env.frame`` (t, m,
aux, unit, blocks), ``env.base`` (the baseline calibration fit, sigma, lattice),
``env.cache`` (a dict for values shared between designs), ``env.to_uT`` and ``env.F_ref``
(the recording's field unit), ``env.field_unit(x, nano)``, ``env.mdot()`` (smoothed dm/dt),
and three of the diagnoser's statistics: ``env.robust_sd(x)``, ``env.time_regressors()``
(the panel's six block regressors) and ``env.solve6(XX21, Xe)`` (their ridge solve). This
module imports nothing from the diagnoser: the forms sit beside the forward models in the
simulator's layer, and the diagnoser hands them what they read.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class MeanForm:
    designs: Callable          # (env) -> list of design dicts
    G: Callable                # (env, design) -> callable(frame, m, state) -> (N, 3, k)
    k: int
    magnitude: Callable        # (env, design, theta) -> {"value": v, "unit": u, ...}
    alias_of: str | None = None    # another effect with the same observable (reported as ambiguous)
    contains: tuple = ()           # effects this form holds as a special case (left out with them)
    # (env) -> (design, text): the setting at which the form turns into another effect; when the
    # data prefer it to every design by a wide margin the effect is not claimed (Engine.limit_excess)
    limit: Callable | None = None

    @property
    def kind(self) -> str:
        return "mean"


@dataclass
class EstimatedForm:
    kind: str                  # "noise", "clock" or "mask"
    estimate: Callable         # (env, ctx, mult) -> params dict or None
    replica: Callable          # (env, params) -> list of (effect object, params) for the simulator
    magnitude: Callable        # (env, params) -> dict
    mask: Callable | None = None   # (env, params, raw (N, 3)) -> (N,) usable samples
    alias_of: str | None = None
    # (env, ctx, mult, spread) -> params: a second estimate, weighted by the spread of the replicas
    # of ``spread`` (an evaluation carrying a previous estimate; None on the first pass), for an
    # effect whose own realisation dominates the first estimate's errors (Engine.extend)
    refine: Callable | None = None


class ReplicaEffect:
    """A replica-side forward model the simulator applies like a library effect (per-axis
    generalisations of the library's own forms, built from an estimate)."""

    def __init__(self, name, stage, fn):
        self.name, self.stage, self.fn = name, stage, fn

    def apply(self, ctx, params):
        self.fn(ctx)


def single_design(env) -> list:
    """The design list of a form with no nonlinear setting."""
    return [{}]


def diag(x):
    """(N, 3, 3) with x (N,) or (N, 3) on the diagonal."""
    x = np.asarray(x)
    out = np.zeros((x.shape[0], 3, 3))
    for j in range(3):
        out[:, j, j] = x if x.ndim == 1 else x[:, j]
    return out


def vec_magnitude(env, theta, scale, unit_nano, per):
    """{"value": |theta scale|, "unit", "vector"} of a fitted 3-vector in the recording's unit."""
    v = np.asarray(theta) * scale
    val, unit = env.field_unit(np.linalg.norm(v), nano=unit_nano)
    comp = [env.field_unit(x, nano=unit_nano)[0] for x in v]
    return {"value": val, "unit": unit + per, "vector": comp}
