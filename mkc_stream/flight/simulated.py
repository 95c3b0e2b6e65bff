"""Simulated flights with known truth for the attitude-aided calibration (tests, tools/study_flight.py).

The attitude is generated here (body -> NED, yaw-pitch-roll ZYX), the magnetometer by the package's
simulator (sim.simulate: soft and hard iron, noise, disturbance bursts), the power signals by
sim.profiles.flight_power, and the interference k * current(t - delay) by an effect of this module.
The log's attitude is the true one with an error: a slowly wandering yaw error (first-order
Gauss-Markov, yaw_error_deg RMS, 30 s correlation time) and 0.3 deg RMS roll/pitch error.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.recording import Recording
from ..sim import SensorModel, Trajectory, simulate
from ..sim.effects.noise import gauss_markov
from ..sim.profiles import flight_power

G = 9.80665


def _euler_to_matrix(yaw, pitch, roll) -> np.ndarray:
    """(N, 3, 3) body -> NED, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.empty((yaw.shape[0], 3, 3))
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = cy * sp * sr - sy * cr
    R[:, 0, 2] = cy * sp * cr + sy * sr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = sy * sp * sr + cy * cr
    R[:, 1, 2] = sy * sp * cr - cy * sr
    R[:, 2, 0] = -sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


def _euler_to_quat(yaw, pitch, roll) -> np.ndarray:
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    return np.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], axis=1)


class _DelayedCurrent:
    """Effect: m += k * current(t - delay) (k in uT/A per axis, delay in s)."""

    stage = "offset"
    name = "delayed_current_hard_iron"

    def apply(self, ctx, params):
        cur = np.interp(ctx.t - params["delay"], ctx.t, ctx.aux["current"])
        ctx.m += cur[:, None] * np.asarray(params["k"], dtype=np.float64)[None, :]


@dataclass
class SimulatedFlight:
    recording: Recording
    truth: dict                 # A, b, S, K (uT/A), delay_s, h_ned, R_true (N,3,3), disturbed, yaw_error_deg


def simulated_flight(duration=300.0, rate=25.0, seed=0, h_ned=(20.0, 1.0, 45.0), hard_iron=(12.0, -7.0, 20.0),
                     soft_iron=None, k_current=(0.1, -0.05, 0.15), delay=0.03, noise=0.1, disturbed=0.0,
                     yaw_error_deg=3.0, tilt_error_deg=0.3, bank_gain=12.0, pitch_amp=0.08, tilt_jitter=0.03,
                     yaw_only=False, i_max=35.0) -> SimulatedFlight:
    """A flight with turns (coordinated bank of bank_gain m/s x turn rate), a slow pitch wave of
    pitch_amp rad and tilt_jitter rad of jitter; yaw_only: a ground robot (no tilt at all).
    Units: uT, A, s, rad unless named _deg."""
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate))
    t = np.arange(n) / float(rate)
    turn = gauss_markov(rng, t, 0.15, 15.0, dims=1)[:, 0]
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (turn[1:] + turn[:-1]) * np.diff(t))]) + rng.uniform(0, 6.3)
    if yaw_only:
        pitch = np.zeros(n)
        roll = np.zeros(n)
    else:
        roll = np.arctan(bank_gain * turn / G) + gauss_markov(rng, t, tilt_jitter, 1.0, dims=1)[:, 0]
        pitch = pitch_amp * np.sin(2 * np.pi * t / 40.0) + gauss_markov(rng, t, tilt_jitter, 1.0, dims=1)[:, 0]
    R = _euler_to_matrix(yaw, pitch, roll)
    h = np.asarray(h_ned, dtype=np.float64)
    F = float(np.linalg.norm(h))
    hb = np.einsum("kji,j->ki", R, h)
    thr, cur, volt = flight_power(t, rng, other_loads=True, i_max=i_max)
    acc = np.einsum("kji,j->ki", R, np.array([0.0, 0.0, -G]))
    traj = Trajectory(t=t, field_dir=hb / F, acc=acc, aux={"throttle": thr, "current": cur, "voltage": volt},
                      name=f"simulated_flight(seed={seed})")
    sensor = SensorModel(field=F, hard_iron=tuple(hard_iron), soft_iron=soft_iron, noise=noise,
                         burst_fraction=disturbed, burst_length=(10, 60))
    sim = simulate(traj, sensor, effects=[(_DelayedCurrent(), {"k": k_current, "delay": delay})], seed=rng)
    # the logged attitude: the true one with a wandering yaw error and a small tilt error
    e_yaw = gauss_markov(rng, t, np.radians(yaw_error_deg), 30.0, dims=1)[:, 0]
    e_tilt = gauss_markov(rng, t, np.radians(tilt_error_deg), 5.0, dims=2)
    q = _euler_to_quat(yaw + e_yaw, pitch + e_tilt[:, 0], roll + e_tilt[:, 1])
    rec = sim.recording
    rec.aux.update(qw=q[:, 0], qx=q[:, 1], qy=q[:, 2], qz=q[:, 3])
    S = sim.truth["soft_iron"]
    truth = {"A": np.linalg.inv(S), "b": np.asarray(hard_iron, dtype=np.float64), "S": S,
             "K": np.asarray(k_current, dtype=np.float64), "delay_s": float(delay), "h_ned": h, "R_true": R,
             "disturbed": sim.truth["disturbed"], "yaw_error_deg": float(yaw_error_deg)}
    return SimulatedFlight(recording=rec, truth=truth)
