"""Trajectories: where the sensor points, and what the aux signals do, sample by sample.

A trajectory gives the true field direction in the sensor frame (unit vectors), the
accelerometer's specific force and the gyroscope's rate (sensor frame), and aux signals. It is
either generated (hand-waving rotations, a figure-8, flight-like segments, a ground vehicle that
only turns about the vertical, a sensor at rest) or taken from a real
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
#: the generated motion kinds (_attitude)
MOTIONS = (
    "hand",       # tumbling: OU yaw and roll rates 1.2 rad/s RMS, pitch sweeps +-83 deg; the whole sphere
    "figure8",    # figure-8s of ~12 s (pitch +-75 deg) while yaw and roll turn round; the whole sphere
    "flight",     # banked turns: OU yaw rate 0.15 rad/s RMS, bank for 12 m/s, pitch +-5 deg; a band
    "ground",     # car/robot: OU yaw rate 0.1 rad/s + a 360 deg turn each 28-70 s, roll/pitch 2 deg RMS
    "static",     # at rest in one random attitude, vibration 0.002 rad RMS per angle (0.1 s); one direction
)
STATIC_JITTER_RAD = 0.002     # rad RMS per attitude angle: the vibration of a sensor at rest
STATIC_JITTER_TAU_S = 0.1     # s, its correlation time
GROUND_SPEED = 1.5            # m/s: the ground vehicle's nominal speed, for its centripetal acceleration


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


def _full_turns(rng, t: np.ndarray) -> np.ndarray:
    """Yaw rate (rad/s) of a vehicle's full turns: each turns 2 pi, left or right, at a mean rate
    wm of 0.25-0.5 rad/s with the raised-cosine profile w(s) = wm (1 - cos(2 pi s / d)),
    d = 2 pi / wm (so its integral over the turn is 2 pi). The first starts within 40 s, each
    next one 15-45 s after the previous one ends: every 100 s holds at least one whole turn."""
    rate = np.zeros_like(t)
    start = t[0] + rng.uniform(0.0, 40.0)
    while start < t[-1]:
        wm = rng.uniform(0.25, 0.5)
        d = 2 * np.pi / wm
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        s = t - start
        on = (s >= 0.0) & (s < d)
        rate[on] += sign * wm * (1.0 - np.cos(2 * np.pi * s[on] / d))
        start += d + rng.uniform(15.0, 45.0)
    return rate


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
    elif kind == "ground":
        # heading wanders (OU yaw rate, 4 s) plus full turns; terrain tilts roll and pitch (OU, 5 s)
        yaw = _integrate(t, _ou(rng, t, 4.0, 0.1) + _full_turns(rng, t)) + rng.uniform(0, 2 * np.pi)
        pitch = _ou(rng, t, 5.0, np.radians(2.0))
        roll = _ou(rng, t, 5.0, np.radians(2.0))
    elif kind == "static":
        # one attitude, uniform over rotations (pitch = arcsin U(-1, 1): the ZYX angles' Haar density
        # is proportional to cos(pitch)), plus the vibration on each angle
        yaw = rng.uniform(-np.pi, np.pi) + _ou(rng, t, STATIC_JITTER_TAU_S, STATIC_JITTER_RAD)
        pitch = np.arcsin(rng.uniform(-1.0, 1.0)) + _ou(rng, t, STATIC_JITTER_TAU_S, STATIC_JITTER_RAD)
        roll = rng.uniform(-np.pi, np.pi) + _ou(rng, t, STATIC_JITTER_TAU_S, STATIC_JITTER_RAD)
    else:
        raise ValueError(f"unknown motion {kind!r}; use {', '.join(MOTIONS)}")
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1))


def _body_rates(t: np.ndarray, R: Rotation) -> np.ndarray:
    d = (R[:-1].inv() * R[1:]).as_rotvec() / np.maximum(np.diff(t), 1e-9)[:, None]
    out = np.empty((len(t), 3))
    out[1:-1] = 0.5 * (d[1:] + d[:-1])
    out[0], out[-1] = d[0], d[-1]
    return out


def _linear_acc(motion: str, t: np.ndarray, R: Rotation, rng, rms: float) -> np.ndarray:
    """Linear acceleration (N, 3), world frame, m/s^2; ``rms`` is generate's linear_acc."""
    if motion == "ground":
        # along the heading: throttle and brakes (OU, RMS rms, 2 s); sideways: the centripetal
        # a = v dpsi/dt at GROUND_SPEED; vertical: terrain bumps (OU, RMS rms / 3, 0.2 s)
        yaw = np.unwrap(R.as_euler("ZYX")[:, 0])
        ahead = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
        left = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], axis=1)
        forward = _ou(rng, t, 2.0, rms)
        sideways = GROUND_SPEED * np.gradient(yaw, t)
        up = _ou(rng, t, 0.2, rms / 3.0)
        return forward[:, None] * ahead + sideways[:, None] * left + up[:, None] * np.array([0.0, 0.0, 1.0])
    if motion == "static":
        # at rest: only the vibration's, RMS rms / 10 per axis (OU, STATIC_JITTER_TAU_S)
        return np.stack([_ou(rng, t, STATIC_JITTER_TAU_S, rms / 10.0) for _ in range(3)], axis=1)
    return np.stack([_ou(rng, t, 0.5, rms) for _ in range(3)], axis=1)


def generate(motion="hand", duration=200.0, rate=50.0, seed=0, temp="cycle", power=False,
             other_loads=True, inclination=60.0, linear_acc=0.3, temp_amplitude=8.0, temp_cycles=3.0):
    """A generated trajectory.

    motion: "hand" (hand-waving tumbling that covers the sphere), "figure8", "flight" (banked
    turns; covers little of the sphere), "ground" (a vehicle turning about the vertical: every
    heading, roll and pitch within a few degrees; a circle of directions, not a sphere) or
    "static" (at rest in one random attitude: one direction). temp: "cycle", "ramp", "const"
    or None (no temp column). power: add flight-like throttle, current and voltage columns
    (other_loads=False makes current a function of throttle alone). linear_acc: RMS of the
    linear acceleration per axis, m/s^2 (ground: along the heading, plus the turns' centripetal
    and a third of it vertically; static: a tenth of it, the vibration's).
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate))
    if n < 10:
        raise ValueError(f"duration x rate gives {n} samples; need at least 10")
    t = np.arange(n) / float(rate)
    R = _attitude(motion, t, rng)
    h = world_field(inclination)
    lin = _linear_acc(motion, t, R, rng, linear_acc)
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
