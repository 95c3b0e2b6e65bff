"""Trajectories: where the sensor points, and what the aux signals do, sample by sample.

A trajectory gives the true field direction in the sensor frame (unit vectors), the
accelerometer's specific force and the gyroscope's rate (sensor frame), and aux signals. It is
either generated (hand-waving rotations, a figure-8, flight-like segments) or taken from a real
recording: its timestamps, the directions implied by its calibrated data, its accelerometer
(which, with the field, fixes the attitude) and its aux columns.

Conventions: world frame ENU (z up); attitude R maps sensor to world; the field points north
and down by the inclination; an accelerometer at rest reads +9.81 m/s^2 along world up.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from . import profiles

G = 9.80665


@dataclass
class Trajectory:
    t: np.ndarray                       # (N,) s
    field_dir: np.ndarray               # (N, 3) unit, sensor frame
    acc: np.ndarray | None = None       # (N, 3) specific force, sensor frame, m/s^2 (noise-free when generated)
    gyro: np.ndarray | None = None      # (N, 3) rad/s
    aux: dict = field(default_factory=dict)
    name: str = ""

    def __post_init__(self):
        self.t = np.asarray(self.t, dtype=np.float64)
        self.field_dir = np.asarray(self.field_dir, dtype=np.float64)

    def __len__(self):
        return int(self.t.shape[0])

    def field_at(self, tq: np.ndarray) -> np.ndarray:
        """Field direction at arbitrary times (component-wise linear interpolation, renormalised)."""
        out = np.stack([np.interp(tq, self.t, self.field_dir[:, j]) for j in range(3)], axis=1)
        return out / np.linalg.norm(out, axis=1, keepdims=True)


def world_field(inclination_deg: float) -> np.ndarray:
    inc = np.radians(inclination_deg)
    return np.array([0.0, np.cos(inc), -np.sin(inc)])


def _ou(rng, t, tau, sigma):
    from .effects.noise import gauss_markov

    return gauss_markov(rng, t, sigma, tau, dims=1)[:, 0]


def _integrate(t, rate):
    return np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t))])


def _attitude(kind: str, t: np.ndarray, rng) -> Rotation:
    """Sensor-to-world attitude for a motion kind, as intrinsic yaw-pitch-roll angles."""
    T = t[-1] - t[0]
    if kind == "hand":
        # rates wander like a hand's, back and forth (zero-mean OU, ~1.2 rad/s, reversing every
        # second or two); pitch sweeps so the whole sphere is visited
        yaw = _integrate(t, _ou(rng, t, 1.5, 1.2))
        pitch = 1.45 * np.sin(_integrate(t, 0.35 + np.abs(_ou(rng, t, 3.0, 0.3))) + rng.uniform(0, 6.3))
        roll = _integrate(t, _ou(rng, t, 1.5, 1.2))
    elif kind == "figure8":
        P = max(T / max(T / 12.0, 1.0), 6.0)           # ~12 s per figure
        s = 2 * np.pi * (t - t[0]) / P
        yaw = 2 * np.pi * (t - t[0]) / (4 * P) + 0.9 * np.sin(s)
        pitch = 1.3 * np.sin(2 * s)
        roll = 2 * np.pi * (t - t[0]) / (3.1 * P) + 0.8 * np.sin(s + 1.0)
    elif kind == "flight":
        turn = _ou(rng, t, 15.0, 0.15)                   # yaw rate of turns, rad/s
        yaw = _integrate(t, turn) + rng.uniform(0, 6.3)
        roll = np.arctan(12.0 * turn / G) + _ou(rng, t, 1.0, 0.03)   # coordinated bank at 12 m/s
        pitch = 0.08 * np.sin(2 * np.pi * (t - t[0]) / 40.0) + _ou(rng, t, 1.0, 0.03)
    else:
        raise ValueError(f"unknown motion {kind!r}; use hand, figure8 or flight")
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1))


def _body_rates(t: np.ndarray, R: Rotation) -> np.ndarray:
    d = (R[:-1].inv() * R[1:]).as_rotvec() / np.maximum(np.diff(t), 1e-9)[:, None]
    out = np.empty((len(t), 3))
    out[1:-1] = 0.5 * (d[1:] + d[:-1])
    out[0], out[-1] = d[0], d[-1]
    return out


def generate(motion="hand", duration=200.0, rate=50.0, seed=0, temp="cycle", power=False,
             other_loads=True, inclination=60.0, linear_acc=0.3, temp_amplitude=8.0, temp_cycles=3.0):
    """A generated trajectory.

    motion: "hand" (hand-waving tumbling that covers the sphere), "figure8", "flight" (banked
    turns; covers little of the sphere). temp: "cycle", "ramp", "const" or None (no temp column).
    power: add flight-like throttle, current and voltage columns (other_loads=False makes
    current a function of throttle alone). linear_acc: RMS of the linear acceleration, m/s^2.
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate))
    if n < 10:
        raise ValueError(f"duration x rate gives {n} samples; need at least 10")
    t = np.arange(n) / float(rate)
    R = _attitude(motion, t, rng)
    h = world_field(inclination)
    lin = np.stack([_ou(rng, t, 0.5, linear_acc) for _ in range(3)], axis=1)
    acc = R.inv().apply(lin + np.array([0.0, 0.0, G]))
    aux = {}
    if temp is not None:
        aux["temp"] = profiles.temperature(t, rng, temp, amplitude=temp_amplitude, cycles=temp_cycles)
    if power:
        aux["throttle"], aux["current"], aux["voltage"] = profiles.flight_power(t, rng, other_loads)
    return Trajectory(t=t, field_dir=R.inv().apply(h), acc=acc, gyro=_body_rates(t, R), aux=aux,
                      name=f"{motion}(duration={duration:g}, rate={rate:g}, seed={seed})")


def moving_average(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average along axis 0 (edges use the samples available)."""
    if width <= 1:
        return x.copy()
    k = np.ones(width) / width
    ones = np.convolve(np.ones(x.shape[0]), k, mode="same")
    cols = [np.convolve(x[:, j], k, mode="same") / ones for j in range(x.shape[1])]
    return np.stack(cols, axis=1)


def cone_project(u: np.ndarray, g: np.ndarray, dip: float) -> np.ndarray:
    """Unit vectors at angle ``dip`` (rad) from g, in the plane of u and g (u where undefined)."""
    c = np.sum(u * g, axis=1, keepdims=True)
    w = u - c * g
    nw = np.linalg.norm(w, axis=1, keepdims=True)
    ok = (nw[:, 0] > 1e-9) & np.isfinite(g).all(axis=1)
    out = u.copy()
    out[ok] = np.cos(dip) * g[ok] + np.sin(dip) * w[ok] / nw[ok]
    return out


def from_recording(rec, b=None, S=None, smooth=5, dip=None):
    """A trajectory replaying a recording: its timestamps, its aux columns, its accelerometer
    and gyroscope, and the field directions implied by its data.

    Directions are u = S (m - b) / |S (m - b)| (b, S from an MKC-EM fit when not given),
    smoothed over ``smooth`` samples; with an accelerometer each u is turned onto the cone of
    constant field-gravity angle ``dip`` (the median angle when not given), which fixes the
    attitude: two non-parallel vectors determine it.
    """
    if b is None or S is None:
        from ..calib.fit import fit_ellipsoid

        fit = fit_ellipsoid(rec.mag, "mkc-em")
        b, S = fit.hard_iron, fit.soft_iron
    mc = (rec.mag - b) @ np.asarray(S).T
    u = moving_average(mc / np.linalg.norm(mc, axis=1, keepdims=True), smooth)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    acc = gyro = None
    if all(c in rec.aux for c in ("ax", "ay", "az")):
        acc = np.stack([rec.aux[c] for c in ("ax", "ay", "az")], axis=1)
        g = acc / np.linalg.norm(acc, axis=1, keepdims=True)
        if dip is None:
            ok = np.isfinite(g).all(axis=1)
            dip = float(np.median(np.arccos(np.clip(np.sum(u[ok] * g[ok], axis=1), -1, 1))))
        u = cone_project(u, g, dip)
    if all(c in rec.aux for c in ("gx", "gy", "gz")):
        gyro = np.stack([rec.aux[c] for c in ("gx", "gy", "gz")], axis=1)
    aux = {k: v for k, v in rec.aux.items() if k not in ("ax", "ay", "az", "gx", "gy", "gz")}
    return Trajectory(t=rec.t.copy(), field_dir=u, acc=acc, gyro=gyro, aux=aux,
                      name=f"recording({rec.path.name if rec.path else 'memory'})")
