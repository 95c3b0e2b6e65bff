"""Aux signal profiles: temperature that ramps or cycles, and flight-like power (throttle,
current, voltage) in segments.

Why these shapes: they are what makes aux-driven effects identifiable. A temperature that
only ramps is confounded with a time drift; cycles are not. A current that is a function of
throttle alone is confounded with a throttle effect; other loads (servos, radios, heaters
switching on and off) make them separable. ``flight_power(..., other_loads=False)`` gives the
confounded case on purpose (the blind benchmark's confusable pairs).
"""
from __future__ import annotations

import numpy as np


def _ou(rng, t, tau, sigma):
    """Ornstein-Uhlenbeck path on t (stationary, exact for any dt)."""
    from .effects.noise import gauss_markov

    return gauss_markov(rng, t, sigma, tau, dims=1)[:, 0]


def _smooth_steps(t, times, levels, rise):
    """Piecewise-constant levels switching at ``times`` with a first-order rise time (s)."""
    from .effects.base import first_order_lag

    idx = np.searchsorted(times, t, side="right") - 1
    return first_order_lag(t, np.asarray(levels)[np.clip(idx, 0, len(levels) - 1)], rise)


def temperature(t, rng, kind="cycle", base=25.0, amplitude=8.0, cycles=3.0, noise=0.02):
    """Board temperature in degC: "cycle" (sinusoid-like, ``cycles`` periods), "ramp"
    (warm-up by ``amplitude`` with a time constant of a third of the recording), "const"."""
    T = t[-1] - t[0] if t.size > 1 else 1.0
    s = (t - t[0]) / max(T, 1e-9)
    if kind == "cycle":
        phase = 2 * np.pi * cycles * s + rng.uniform(0, 2 * np.pi)
        x = base + amplitude * (np.sin(phase) + 0.25 * np.sin(2.3 * phase + 1.0)) / 1.1
    elif kind == "ramp":
        x = base + amplitude * (1.0 - np.exp(-3.0 * s))
    elif kind == "const":
        x = np.full_like(t, base)
    else:
        raise ValueError(f"unknown temperature profile {kind!r}; use cycle, ramp or const")
    return x + _ou(rng, t, 20.0, 0.1) + rng.normal(0.0, noise, t.shape)


def flight_power(t, rng, other_loads=True, i_max=25.0, v_full=16.8):
    """(throttle 0..1, current A, voltage V) of a flight in segments: idle, climb, cruise,
    hover, descent, each 8-40 s, with gusty fluctuations; current = idle + i_max throttle^1.5
    (+ other loads switching on and off), voltage sags with current and discharge."""
    from .effects.base import first_order_lag

    T = t[-1] - t[0]
    times, levels = [t[0]], [0.08]
    while times[-1] < t[-1]:
        times.append(times[-1] + rng.uniform(8.0, 40.0))
        levels.append(rng.choice([0.08, 0.35, 0.45, 0.55, 0.7, 0.85]) + rng.uniform(-0.05, 0.05))
    thr = _smooth_steps(t, np.array(times), np.array(levels), 1.0)
    thr = np.clip(thr + _ou(rng, t, 0.5, 0.03), 0.0, 1.0)
    current = 0.6 + i_max * thr ** 1.5
    if other_loads:
        for amp in (rng.uniform(2.0, 5.0), rng.uniform(1.0, 3.0)):
            sw = np.cumsum(rng.uniform(5.0, 30.0, size=int(T / 5) + 4)) + t[0]
            on = (np.searchsorted(sw, t) % 2 == 1).astype(np.float64)
            current = current + amp * first_order_lag(t, on, 0.2)
    current = current + rng.normal(0.0, 0.05, t.shape)
    voltage = v_full - 0.02 * current - 1.2 * (t - t[0]) / max(T, 1.0) + rng.normal(0.0, 0.01, t.shape)
    return thr, current, voltage
