"""Synthetic magnetometer streams with known calibration and burst disturbances.

Used by tests and the accuracy studies in tools/. A recording is raw = S^-1 (F u) + b + noise
(+ burst offsets), with u(t) a smooth path over the sphere (a hand-held figure sweep), so the
true calibration (b, S, F) of the spec's convention is known exactly.

The simulator's ``sweep`` preset (:func:`mkc_stream.sim.presets.sweep`) makes the same stream
through :func:`mkc_stream.sim.simulate`, sample for sample, and can add library effects to it;
the path, platform, burst and spike generators here are the ones it uses. ``synthetic_mag``
stays here, written out, because the calibration layer's tests and studies need it and the
simulator sits above this layer (tests/test_effect_registry.py checks the two agree).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class SyntheticMag:
    t: np.ndarray
    raw: np.ndarray            # (N, 3) raw samples
    hard_iron: np.ndarray      # true b
    soft_iron: np.ndarray      # true S (symmetric PD, det 1)
    field: float               # true F
    disturbed: np.ndarray      # (N,) bool, True inside a burst or at a spike
    directions: np.ndarray     # (N, 3) true unit field directions in the sensor frame


def random_soft_iron(rng, spread=0.25):
    """Symmetric PD S with det 1 and eigenvalues within about exp(+-spread)."""
    lam = np.exp(rng.uniform(-spread, spread, 3))
    lam /= np.prod(lam) ** (1 / 3)
    Q = Rotation.random(random_state=rng).as_matrix()
    S = (Q * lam) @ Q.T
    return 0.5 * (S + S.T)


def random_platform(rng, hard_iron_scale=30.0, soft_spread=0.25):
    """(b, S): hard iron uniform in +-hard_iron_scale per axis (uT), then a random soft iron."""
    b = rng.uniform(-hard_iron_scale, hard_iron_scale, 3)
    return b, random_soft_iron(rng, soft_spread)


def spike_offsets(seed, N, fraction, magnitude):
    """(hit (N,) bool, offsets (hits, 3)): each sample is a spike with probability ``fraction`` and
    gets N(0, magnitude^2) per axis, drawn from their own generator (seeded [seed, 1]) so a stream
    without spikes draws nothing extra."""
    srng = np.random.default_rng([seed, 1])
    hit = srng.random(N) < fraction
    return hit, srng.normal(0.0, magnitude, (int(hit.sum()), 3))


def sphere_sweep(rng, N, turns=None):
    """Unit vectors along a pole-to-pole spiral (back and forth), randomly rotated, with jitter."""
    turns = turns if turns is not None else max(4.0, N / 150.0)
    s = np.linspace(0.0, 1.0, N)
    passes = 2.0
    z = np.cos(np.pi * passes * s)               # pole -> pole -> pole
    phi = 2 * np.pi * turns * s + rng.uniform(0, 2 * np.pi)
    r = np.sqrt(np.clip(1 - z * z, 0, None))
    u = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    u += 0.03 * np.cumsum(rng.normal(size=(N, 3)), axis=0) / np.sqrt(np.arange(1, N + 1))[:, None]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u @ Rotation.random(random_state=rng).as_matrix().T


def burst_mask_and_offsets(rng, N, fraction, length=(20, 60), magnitude=(5.0, 40.0)):
    """Offsets (N, 3) made of constant-vector bursts covering about `fraction` of the samples."""
    offs = np.zeros((N, 3))
    mask = np.zeros(N, dtype=bool)
    target = int(round(fraction * N))
    guard = 0
    while mask.sum() < target and guard < 10000:
        guard += 1
        L = int(rng.integers(length[0], length[1] + 1))
        L = min(L, target - int(mask.sum())) if target - mask.sum() < length[0] else L
        start = int(rng.integers(0, max(1, N - L)))
        if mask[max(0, start - 5):start + L + 5].any():
            continue
        v = rng.normal(size=3)
        v *= rng.uniform(*magnitude) / np.linalg.norm(v)
        offs[start:start + L] = v
        mask[start:start + L] = True
    return mask, offs


def synthetic_mag(seed=0, N=2000, field=50.0, noise=0.3, burst_fraction=0.1, burst_length=(20, 60),
                  burst_magnitude=(5.0, 40.0), hard_iron_scale=30.0, soft_spread=0.25, rate_hz=50.0,
                  spike_fraction=0.0, spike_magnitude=1000.0):
    """A synthetic raw magnetometer recording with known truth (units: uT unless scaled).

    Bursts are slow disturbances (a motor, a phone); spikes are isolated gross readings (a glitched
    bus transfer, a saturated axis): each sample is one with probability spike_fraction and gets a
    N(0, spike_magnitude^2) offset per axis. Spikes come from their own generator, so a recording
    without them is the same as before they existed; `disturbed` marks bursts and spikes.
    """
    rng = np.random.default_rng(seed)
    b, S = random_platform(rng, hard_iron_scale, soft_spread)
    u = sphere_sweep(rng, N)
    clean = (field * u) @ np.linalg.inv(S).T + b
    mask, offs = burst_mask_and_offsets(rng, N, burst_fraction, burst_length, burst_magnitude)
    raw = clean + offs + noise * rng.normal(size=(N, 3))
    if spike_fraction > 0:
        spikes, offsets = spike_offsets(seed, N, spike_fraction, spike_magnitude)
        raw[spikes] += offsets
        mask = mask | spikes
    t = np.arange(N) / rate_hz
    return SyntheticMag(t=t, raw=raw, hard_iron=b, soft_iron=S, field=field, disturbed=mask, directions=u)
