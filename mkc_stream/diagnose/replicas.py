"""Replicas: the simulator replayed on the recording's own timestamps, directions and aux signals.

* norm channel: :func:`mkc_stream.sim.simulate` with the baseline sensor (fitted b, S, F,
  white noise per axis, bursts like the recording's) along the recording's directions, plus any
  stochastic effect of the model; the channel is computed at the simulated truth.
* dip channel: the accelerometer is not simulated (its linear accelerations cannot be
  reconstructed), so the replica's dip residual is the model's own dip residual shifted in
  time, running on backwards where the recording ends (:func:`shifted`): the same distribution,
  spectrum and dynamics, no tie to orientation, rotation rate or aux signals. A misalignment or latency then shows as
  structure the shifted copies lack.
* clock: a regular clock at the recording's median period (rounded to its timestamp quantum),
  plus the model's clock effects.

Replica k always uses seed ``seed + k``, so two models are compared on common random numbers.
"""
from __future__ import annotations

import numpy as np

from ..sim.effects.base import SimContext
from ..sim.sensor import simulate
from .model import channels


def norm_replicas(frame, base, effects, R, seed, sensor=None):
    """(r_norm (R, N), raw (R, N, 3)) of R simulations of the baseline sensor plus ``effects``."""
    N = frame.n
    r = np.empty((R, N))
    raw = np.empty((R, N, 3))
    st = base.fit.state
    for k in range(R):
        sim = simulate(base.traj, sensor or base.sensor, effects=effects, seed=seed + k)
        raw[k] = sim.mag_full
        r[k] = channels(sim.mag_full, _NormOnly(frame), st).r[:, 0]
    return r, raw


class _NormOnly:
    """A view of a frame without the accelerometer (the norm channel only)."""

    acc_unit = None

    def __init__(self, frame):
        self.frame = frame


def shifted(x, valid, rng):
    """A window of x's valid samples taken out of their mirrored periodic extension
    [x, x reversed]: a shift in time that runs on, backwards, where the recording ends.

    Why mirrored, not circular: a circular shift joins the recording's end to its start, and
    that jump, the same in every replica, is the only thing that tells a replica's
    shift-invariant statistics (the Allan variance at one sample, the block-to-block changes)
    from the real recording's; against that degenerate null a jump of a few sigma read as a
    gap of z 5-8 on nulls. The mirrored extension has no jump, and a window of it holds a
    different stretch of the recording in every replica, so those statistics get a spread.

    Why not a phase-randomised surrogate: the dip residual is heavy-tailed (linear accelerations)
    and non-Gaussian surrogates either miss its distribution or whiten its spectrum, and the
    panel would then see a gap in every real recording. A shifted window keeps the distribution,
    the spectrum and the dynamics and only breaks the tie to orientation, rates and aux signals,
    which is what the dip statistics test.
    """
    xv = x[valid]
    n = xv.size
    out = x.copy()
    if n < 8:
        return out
    k = int(rng.integers(0, 2 * n))
    out[valid] = np.take(np.concatenate([xv, xv[::-1]]), np.arange(k, k + n), mode="wrap")
    return out


def dip_replicas(e_dip, valid, R, seed):
    out = np.empty((R, e_dip.size))
    for k in range(R):
        out[k] = shifted(e_dip, valid, np.random.default_rng(10_000 + seed + k))
    return out


def clock_replicas(frame, base, effects, R, seed):
    """Reported timestamps of R regular clocks with the model's clock effects."""
    ck = base.clock
    n = int(round(frame.duration / ck["dt0"])) + 1
    grid = ck["t0"] + ck["dt0"] * np.arange(n)
    out = []
    for k in range(R):
        rng = np.random.default_rng(20_000 + seed + k)
        ctx = SimContext(t=grid, B=np.zeros((n, 3)), m=np.zeros((n, 3)), aux={}, b=np.zeros(3), S=np.eye(3),
                         F=1.0, rng=rng, t_out=grid.copy(), keep=np.ones(n, dtype=bool))
        for eff, params in effects:
            eff.apply(ctx, params)
        t = ctx.t_out[ctx.keep]
        if ck["quantum"] > 0:
            q, ph = ck["quantum"], ck["phase"]
            t = np.round((t - ck["t0"] - ph) / q) * q + ph + ck["t0"]
        out.append(t)
    return out
