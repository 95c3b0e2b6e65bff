#!/usr/bin/env python
"""An independent simulator of null recordings: a magnetometer, accelerometer and gyroscope
with nothing the diagnosis lists as an effect; effects come only from a caller's injector.

    python tools/indep_sim.py --samples 10000 --seed 3 --out null.csv

:func:`simulate_null` makes the null. :func:`simulate` makes the same recording (every draw
the same) and can add a flight or hand-held session's aux columns (throttle, current, voltage,
and a board temperature from its own thermal model: :func:`throttle_schedule`,
:func:`power_and_heat`) and call an injector at each stage of the signal chain (``STAGES``,
:class:`Scene`): on the true field before the soft and hard iron, on the reading before the
noise, after it, after rounding, and on the clock. tools/blind_indep.py injects the blind
benchmark's effects with it.

Written without :mod:`mkc_stream.sim` or :mod:`mkc_stream.calib.synthetic` (tests/test_null_suite.py
parses the imports), so that the diagnosis's false-alarm rate is also measured on recordings
whose conventions it was not developed against. Only the recording type and its writer come
from the package.

What it draws, all in its own conventions:

* attitude: a unit quaternion q (Hamilton, scalar first) rotating body vectors into a
  north-east-down world frame, driven by a body angular velocity w whose angular acceleration
  a is an Ornstein-Uhlenbeck process per axis:
  da = -a / tau_a dt + sqrt(2 / tau_a) s_a dW,  dw = (a - w / tau_w) dt,
  integrated on a grid of ``SUBSTEPS`` points per sample by the midpoint rule,
  q <- q (x) exp(((w_i + w_{i+1}) / 2) h / 2), so that the attitude and the gyroscope's
  instantaneous rate w(t_k) refer to the same instant (no delay between them).
* field: strength 25-65 uT, inclination -70..75 deg (positive down), any declination, NED.
* platform: m = A (R^T h) + b + n with A symmetric positive definite (eigenvectors a random
  rotation, log-eigenvalues normal with a spread of 0.03-0.15; det A is not 1, the calibration
  absorbs it into the field strength); b a random direction, 5-80 uT. A is symmetric because a
  rotation between the magnetometer and the accelerometer frames is an effect of the library
  (misalignment), not a null.
* noise: white Gaussian, its own level per axis (0.03-0.4 uT times 0.7-1.4 per axis; the
  same on every axis with ``isotropic_noise``).
* accelerometer: specific force R^T (a_lin - g), g = (0, 0, 9.80665) m/s^2 down in NED, with
  a world-frame linear acceleration (Ornstein-Uhlenbeck, 0.1-0.4 m/s^2, 0.1-0.5 s) and white
  noise; no bias or scale error (both would tie the dip to the attitude, which the baseline
  does not model).
* gyroscope: G (w + c) + white noise, with a constant bias c (+-0.03 rad/s) and a gain matrix
  G (scale errors of 2% RMS, 1% cross-axis): the diagnosis fits the gyroscope's map and bias.
* clock: a regular clock; the output data rate is 20, 50 or 100 Hz off by up to 0.5%, its
  period a whole number of microseconds, and the time starts at the device's uptime (10-3600 s).
  Timestamp jitter and lost samples are effects of the library, so a null has neither.
* temperature: ambient 10-35 degC plus self-heating (1-6 degC, time constant 30-300 s) plus a
  slow wander, read with a 0.01 degC resolution; the magnetometer does not depend on it.
* values: the magnetometer, accelerometer and gyroscope are rounded to 32-bit floats (a driver
  reporting floats). Rounding to a coarser LSB (``lsb``, off by default) is the library's
  ``quantization`` effect, which the baseline does not have, so a rounded recording is not a null.
"""
from __future__ import annotations

import argparse
import math
import pathlib
import sys

import numpy as np
from scipy.signal import lfilter

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from mkc_stream.io.recording import Recording  # noqa: E402

#: attitude integration points per sample
SUBSTEPS = 4
GRAVITY = 9.80665                     # m/s^2
ODR_HZ = (20.0, 50.0, 100.0)          # nominal output data rates
TEMP_RESOLUTION = 0.01                # degC


def ou_paths(rng, n, h, tau, sigma, dims):
    """(n, dims) stationary Ornstein-Uhlenbeck paths with step h (s), correlation time tau (s)
    and standard deviation sigma: x_{i+1} = phi x_i + sigma sqrt(1 - phi^2) e_i, phi = exp(-h / tau)."""
    phi = math.exp(-h / tau)
    e = rng.normal(size=(n, dims)) * sigma * math.sqrt(1.0 - phi * phi)
    e[0] = rng.normal(size=dims) * sigma            # start in the stationary law
    return lfilter([1.0], [1.0, -phi], e, axis=0)


def angular_velocity(rng, n, h, rate_sd, tau_a, tau_w):
    """(n, 3) body rate, rad/s: w' = a - w / tau_w driven by an OU angular acceleration a
    (correlation time tau_a, s).

    Stationary variance of w for an OU input of variance s_a^2 and time constant tau_a through
    the first-order lag tau_w: var w = s_a^2 tau_a tau_w^2 / (tau_a + tau_w); s_a is set from it."""
    s_a = rate_sd * math.sqrt((tau_a + tau_w) / (tau_a * tau_w * tau_w))
    a = ou_paths(rng, n, h, tau_a, s_a, 3)
    # exact step of the lag for an input held over each step: w_{i+1} = c w_i + tau_w (1 - c) a_i
    c = math.exp(-h / tau_w)
    w0 = rng.normal(size=3) * rate_sd
    w = lfilter([0.0, tau_w * (1.0 - c)], [1.0, -c], a, axis=0, zi=w0[None, :])[0]
    return w


def integrate_attitude(q0, w, h):
    """Unit quaternions (n, 4), scalar first, body to world: q_{i+1} = q_i (x) exp(wbar h / 2)
    with wbar = (w_i + w_{i+1}) / 2 the body rate over the step (midpoint rule)."""
    n = w.shape[0]
    wb = 0.5 * (w[1:] + w[:-1]) * h                    # rotation vector of each step (body frame)
    ang = np.linalg.norm(wb, axis=1)
    half = 0.5 * ang
    k = np.where(ang > 1e-15, np.sin(half) / np.maximum(ang, 1e-300), 0.5)
    dq = np.column_stack([np.cos(half), wb * k[:, None]]).tolist()
    out = np.empty((n, 4))
    a0, a1, a2, a3 = (float(x) for x in q0)
    out[0] = (a0, a1, a2, a3)
    for i, (b0, b1, b2, b3) in enumerate(dq, start=1):
        a0, a1, a2, a3 = (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3, a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
                          a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1, a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)
        s = 1.0 / math.sqrt(a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3)
        a0, a1, a2, a3 = a0 * s, a1 * s, a2 * s, a3 * s
        out[i] = (a0, a1, a2, a3)
    return out


def world_to_body(q, v):
    """R(q)^T v for unit quaternions q (n, 4) and world vectors v (n, 3) or (3,): the body-frame view."""
    q0, qv = q[:, :1], q[:, 1:]
    v = np.broadcast_to(v, qv.shape)
    # R^T v is the rotation by the conjugate quaternion: v + 2 q0 (v x qv) + 2 qv x (qv x v)
    t = 2.0 * np.cross(v, qv)
    return v + q0 * t + np.cross(t, qv)


def random_rotation(rng):
    """A uniformly random rotation matrix (from a normalised Gaussian quaternion)."""
    a, b, c, d = rng.normal(size=4)
    s = math.sqrt(a * a + b * b + c * c + d * d)
    a, b, c, d = a / s, b / s, c / s, d / s
    return np.array([[a*a + b*b - c*c - d*d, 2*(b*c - a*d), 2*(b*d + a*c)],
                     [2*(b*c + a*d), a*a - b*b + c*c - d*d, 2*(c*d - a*b)],
                     [2*(b*d - a*c), 2*(c*d + a*b), a*a - b*b - c*c + d*d]])


def draw_platform(rng):
    """Field (NED, uT), soft-iron map A (3x3, symmetric positive definite) and hard iron b (uT)."""
    F = rng.uniform(25.0, 65.0)
    inc, dec = np.radians(rng.uniform(-70.0, 75.0)), rng.uniform(0.0, 2 * np.pi)
    h = F * np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])
    V = random_rotation(rng)
    A = V @ np.diag(np.exp(rng.normal(0.0, rng.uniform(0.03, 0.15), 3))) @ V.T
    d = rng.normal(size=3)
    b = rng.uniform(5.0, 80.0) * d / np.linalg.norm(d)
    return h, 0.5 * (A + A.T), b


def _f32(x):
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def _first_order(x, h, tau, x0=None):
    """y' = (x - y) / tau on a grid of step h (s), x held over each step (exact step):
    y_{i+1} = c y_i + (1 - c) x_i, c = exp(-h / tau); y_0 = x0 (default x_0)."""
    c = math.exp(-h / tau)
    y0 = x[0] if x0 is None else x0
    return lfilter([0.0, 1.0 - c], [1.0, -c], x) + y0 * c ** np.arange(x.size)


def _telegraph(rng, rel, mean_dwell):
    """A 0/1 switching load on the times rel (s, from 0): exponential dwell times of mean mean_dwell (s)."""
    edges = np.cumsum(rng.exponential(mean_dwell, size=int(rel[-1] / mean_dwell * 3) + 8))
    return (np.searchsorted(edges, rel) + int(rng.integers(2))) % 2 == 1


def throttle_schedule(rng, rel, h, session):
    """Throttle 0..1 on the times rel (s from the start, step h).

    flight: disarmed on the ground 3-15 s at each end (and, half the time, a 10-40 s landing in
    the middle), a drawn hover throttle (0.38-0.58) while airborne, manoeuvres as raised-cosine
    bumps (one per 12 s on average, 1.5-10 s long, +-0.15 RMS) and gusts (an OU process, 0.2-0.8 s,
    0.01-0.04). The take-offs and landings spool over 2 s (a Hann-window smoothing of the
    airborne mask). hand: a bench session, the stick held at a level (0-0.8, 0 a third of the
    time) for 3-30 s and moved to the next over 0.5-3 s, with a hand's tremor (0.3 s, 0.005)."""
    T = rel[-1]
    if session == "flight":
        air = np.ones(rel.size)
        air[rel < rng.uniform(3.0, 15.0)] = 0.0
        air[rel > T - rng.uniform(3.0, 15.0)] = 0.0
        if rng.uniform() < 0.5:
            t_land = rng.uniform(0.3, 0.7) * T
            air[(rel > t_land) & (rel < t_land + rng.uniform(10.0, 40.0))] = 0.0
        win = np.hanning(max(3, int(round(2.0 / h)) | 1))
        air = np.convolve(air, win / win.sum(), mode="same")
        thr = np.full(rel.size, rng.uniform(0.38, 0.58))
        for _ in range(rng.poisson(T / 12.0)):
            c, w, a = rng.uniform(0.0, T), rng.uniform(1.5, 10.0), rng.normal(0.0, 0.15)
            inside = np.abs(rel - c) < w / 2
            thr[inside] += a * 0.5 * (1.0 + np.cos(2 * np.pi * (rel[inside] - c) / w))
        thr += ou_paths(rng, rel.size, h, rng.uniform(0.2, 0.8), rng.uniform(0.01, 0.04), 1)[:, 0]
        return np.clip(air * thr, 0.0, 1.0)
    if session == "hand":
        knots_t, knots_v, tk = [0.0], [0.0], 0.0
        while tk < T:
            level = 0.0 if rng.uniform() < 1 / 3 else rng.uniform(0.05, 0.8)
            tk += rng.uniform(0.5, 3.0)
            knots_t.append(tk)
            knots_v.append(level)
            tk += rng.uniform(3.0, 30.0)
            knots_t.append(tk)
            knots_v.append(level)
        thr = np.interp(rel, knots_t, knots_v) + ou_paths(rng, rel.size, h, 0.3, 0.005, 1)[:, 0]
        return np.clip(thr, 0.0, 1.0)
    raise ValueError(f"unknown session {session!r}; use flight or hand")


def power_and_heat(rng, rel, h, thr, other_loads=True, thermal="load"):
    """(current A, voltage V, board temperature degC, true current A) for a throttle thr.

    Current: motors draw I_max (c thr^3 + (1 - c) thr^2) (propeller power grows as the cube of
    the speed, winding losses as its square; I_max 15-60 A, c 0.3-0.7), through the motors' and
    ESCs' response (first order, 30-120 ms), plus avionics (0.3-1.0 A) and, with other_loads,
    two loads switching on and off (0.8-4 A each, exponential dwell of 4-25 s mean, 50 ms rise);
    read by a Hall sensor with 0.03-0.15 A noise and a 0.01 A resolution.
    Voltage: a pack of 3-6 cells (1.5-6 Ah, internal resistance 0.02-0.12 ohm), open-circuit
    voltage per cell 3.45 + 0.75 s - 0.4 exp(-12 s) at the state of charge s (starts 0.6-1.0,
    falls with the charge drawn), minus I R; 3-20 mV noise, 1 mV resolution.
    Board temperature (thermal="load"): T' = (T_amb + k I - T) / tau, a board heated in
    proportion to the current (k: 5-15 degC at the session's peak current) and cooled faster
    in the propeller's wash (tau 40-200 s divided by 1 + 0.8 thr), the ambient wandering (OU,
    300 s, 1.5 degC) and moving by +-2-8 degC every 80-250 s (the board carried between places),
    starting at the ambient. thermal="ramp": a warm-up only (the board reaches T_amb + 6-12 degC
    with a time constant of a quarter to half of the recording, no load or ambient change).
    Read with 0.01-0.05 degC noise and a 1/16 degC resolution (a 12-bit digital sensor)."""
    n = rel.size
    i_max, c3 = rng.uniform(15.0, 60.0), rng.uniform(0.3, 0.7)
    motor = _first_order(i_max * (c3 * thr ** 3 + (1.0 - c3) * thr ** 2), h, rng.uniform(0.03, 0.12))
    current = rng.uniform(0.3, 1.0) + motor
    if other_loads:
        for _ in range(2):
            amp, dwell = rng.uniform(0.8, 4.0), rng.uniform(4.0, 25.0)
            current = current + amp * _first_order(_telegraph(rng, rel, dwell).astype(np.float64), h, 0.05)
    cells, cap_ah, r_int = int(rng.integers(3, 7)), rng.uniform(1.5, 6.0), rng.uniform(0.02, 0.12)
    soc = rng.uniform(0.6, 1.0) - np.cumsum(current) * h / 3600.0 / cap_ah
    soc = np.clip(soc, 0.0, 1.0)
    ocv = cells * (3.45 + 0.75 * soc - 0.4 * np.exp(-12.0 * soc))
    voltage = ocv - r_int * current + rng.normal(0.0, rng.uniform(0.003, 0.02), n)
    amb0 = rng.uniform(5.0, 35.0)
    if thermal == "load":
        k = rng.uniform(5.0, 15.0) / max(float(np.max(current)), 1e-9)          # degC/A
        tau = rng.uniform(40.0, 200.0) / (1.0 + 0.8 * thr)
        edges = np.cumsum(rng.uniform(80.0, 250.0, size=int(rel[-1] / 80.0) + 2))
        moves = np.r_[0.0, np.cumsum(rng.choice([-1.0, 1.0], edges.size) * rng.uniform(2.0, 8.0, edges.size))]
        amb = amb0 + moves[np.searchsorted(edges, rel)] + ou_paths(rng, n, h, 300.0, 1.5, 1)[:, 0]
        target = amb + k * current
        # T_{i+1} = target_i + (T_i - target_i) exp(-h / tau_i): exact for a target and tau held over a step
        decay = np.exp(-h / tau)
        temp = np.empty(n)
        temp[0] = amb[0]
        for i in range(n - 1):
            temp[i + 1] = target[i] + (temp[i] - target[i]) * decay[i]
    elif thermal == "ramp":
        rise, tau = rng.uniform(6.0, 12.0), rng.uniform(0.25, 0.5) * max(rel[-1], h)
        temp = amb0 + rise * (1.0 - np.exp(-rel / tau))
    else:
        raise ValueError(f"unknown thermal model {thermal!r}; use load or ramp")
    temp_read = np.round((temp + rng.normal(0.0, rng.uniform(0.01, 0.05), n)) * 16.0) / 16.0
    current_read = np.round((current + rng.normal(0.0, rng.uniform(0.03, 0.15), n)) / 0.01) * 0.01
    return current_read, np.round(voltage, 3), temp_read, current


#: stages at which an injector is called, in order: ``field`` (the true field at the sensor,
#: ``scene.B``, before the soft and hard iron), ``offset`` (``scene.m`` = A B + b, before the
#: noise: fields of nearby sources), ``sensor`` (gain and shape errors of the sensor, still
#: before the noise), ``noise`` (after the white noise), ``range`` (after the optional LSB
#: rounding: clipping, quantizers), ``clock`` (``scene.t_out`` and ``scene.keep``).
STAGES = ("field", "offset", "sensor", "noise", "range", "clock")


class Scene:
    """What an injector may read and change (uT, s, degC, A, V, throttle 0..1).

    t: true sample instants; t_out: reported timestamps; keep: the samples that are recorded;
    B: true field in the sensor frame before the soft and hard iron; m: the reading under
    construction (None at the field stage); A, b: soft-iron map and hard iron (m = A B + b
    + noise), S = A^-1 (the calibration's correction, m_cal = S (m - b)); noise: per-axis
    white noise, uT; aux: the recorded aux columns; current_true: the current before its
    sensor; acc_true: specific force without noise (m/s^2, body frame); truth: the injector's
    notes (returned as truth["injected"])."""

    def __init__(self, **kw):
        self.__dict__.update(kw)
        self.truth = {}

    @property
    def n(self):
        return int(self.t.shape[0])


def simulate(samples=10000, seed=0, inject=None, session=None, other_loads=True, thermal="load", lsb=0.0,
             rate_hz=None, noise_scale=1.0, isotropic_noise=False):
    """(Recording, truth). With inject None and session None, the null recording of
    :func:`simulate_null` (every draw the same, in the same order).

    session: None (temp column only, as in a null), "flight" or "hand": the recording also
    gets throttle, current and voltage columns and its temp column comes from the board's
    thermal model (:func:`throttle_schedule`, :func:`power_and_heat`; other_loads False makes
    current a function of throttle alone, thermal "ramp" a warm-up only). These draws come
    after all of the null's, so the sensor, attitude and noise are those of the null of the same seed.
    inject: None or a callable inject(stage, scene) called once per stage in STAGES order
    (:class:`Scene`); it changes the scene in place. truth["scene"] is the scene."""
    if samples < 10:
        raise ValueError(f"samples must be at least 10, got {samples}")
    if not (noise_scale >= 0 and math.isfinite(noise_scale)):
        raise ValueError(f"noise_scale must be a finite value >= 0, got {noise_scale}")
    if lsb < 0 or not math.isfinite(lsb):
        raise ValueError(f"lsb must be a finite value >= 0 uT, got {lsb}")
    if session not in (None, "flight", "hand"):
        raise ValueError(f"unknown session {session!r}; use None, flight or hand")
    if thermal not in ("load", "ramp"):
        raise ValueError(f"unknown thermal model {thermal!r}; use load or ramp")
    rng = np.random.default_rng(seed)
    odr = float(rate_hz) if rate_hz else float(rng.choice(ODR_HZ))
    period_us = int(round(1e6 / (odr * (1.0 + rng.uniform(-0.005, 0.005)))))
    dt = period_us * 1e-6
    t0_us = int(rng.uniform(10.0, 3600.0) * 1e6)
    t = (t0_us + period_us * np.arange(samples, dtype=np.int64)) / 1e6      # s

    # every setting is drawn before any path, so a seed gives the same platform at every length
    h_field, A, b = draw_platform(rng)
    rate_sd = rng.uniform(0.5, 1.3)                         # rad/s RMS per body axis
    tau_a, tau_w = rng.uniform(0.2, 0.6), rng.uniform(1.0, 4.0)
    sigma = noise_scale * rng.uniform(0.03, 0.4) * rng.uniform(0.7, 1.4, 3)           # uT per axis
    lin_sd, lin_tau = rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.5)
    acc_noise = rng.uniform(0.01, 0.08)
    gyro_bias = rng.uniform(-0.03, 0.03, 3)
    gain = np.eye(3) + np.diag(rng.normal(0.0, 0.02, 3)) + (1 - np.eye(3)) * rng.normal(0.0, 0.01, (3, 3))
    gyro_noise = rng.uniform(0.002, 0.01)
    heat, tau_heat, ambient = rng.uniform(1.0, 6.0), rng.uniform(30.0, 300.0), rng.uniform(10.0, 35.0)
    q0 = rng.normal(size=4)
    if isotropic_noise:
        sigma = np.full(3, np.sqrt(np.mean(sigma ** 2)))

    h = dt / SUBSTEPS
    n_fine = (samples - 1) * SUBSTEPS + 1
    w_fine = angular_velocity(rng, n_fine, h, rate_sd, tau_a, tau_w)
    q = integrate_attitude(q0 / np.linalg.norm(q0), w_fine, h)[::SUBSTEPS]
    w = w_fine[::SUBSTEPS]

    mag_noise = rng.normal(size=(samples, 3)) * sigma
    lin = ou_paths(rng, samples, dt, lin_tau, lin_sd, 3)
    acc_true = world_to_body(q, lin - np.array([0.0, 0.0, GRAVITY]))
    acc = acc_true + rng.normal(0.0, acc_noise, (samples, 3))
    gyro = (w + gyro_bias) @ gain.T + rng.normal(0.0, gyro_noise, (samples, 3))
    rel = t - t[0]
    temp = (ambient + heat * (1.0 - np.exp(-rel / tau_heat)) + ou_paths(rng, samples, dt, 120.0, 0.3, 1)[:, 0])
    temp = np.round(temp / TEMP_RESOLUTION) * TEMP_RESOLUTION
    aux = {"ax": _f32(acc[:, 0]), "ay": _f32(acc[:, 1]), "az": _f32(acc[:, 2]),
           "gx": _f32(gyro[:, 0]), "gy": _f32(gyro[:, 1]), "gz": _f32(gyro[:, 2]), "temp": temp}
    current_true = None
    if session is not None:
        thr = throttle_schedule(rng, rel, dt, session)
        current, voltage, aux["temp"], current_true = power_and_heat(rng, rel, dt, thr, other_loads, thermal)
        aux.update(throttle=np.round(thr, 4), current=current, voltage=voltage)

    scene = Scene(t=t, t_out=t.copy(), keep=np.ones(samples, dtype=bool), B=world_to_body(q, h_field), m=None,
                  A=A, b=b, S=np.linalg.inv(A), noise=sigma, aux=aux, current_true=current_true,
                  acc_true=acc_true)

    def run(stage):
        if inject is not None:
            inject(stage, scene)

    run("field")
    scene.m = scene.B @ A.T + b
    run("offset")
    run("sensor")
    scene.m = scene.m + mag_noise
    run("noise")
    if lsb > 0:
        scene.m = np.round(scene.m / lsb) * lsb
    run("range")
    run("clock")

    keep = scene.keep
    meta = {"source": "tools/indep_sim.py", "units.mag": "uT", "units.acc": "m/s^2", "units.gyr": "rad/s",
            "rate_hz": f"{1.0 / dt:.6g}", "seed": str(seed)}
    if session is not None:
        meta.update({"units.temp": "degC", "units.current": "A", "units.voltage": "V", "units.throttle": "0..1"})
    if keep.all():
        rec = Recording(t=scene.t_out, mag=_f32(scene.m), aux=aux, meta=meta)
    else:
        rec = Recording(t=scene.t_out[keep], mag=_f32(scene.m[keep]), aux={k: v[keep] for k, v in aux.items()},
                        meta=meta)
    truth = {"field_ned_uT": h_field, "field_uT": float(np.linalg.norm(h_field)), "soft_iron_map": A,
             "hard_iron_uT": b, "noise_uT": sigma, "lsb_uT": float(lsb), "period_s": dt, "odr_hz": odr,
             "rate_sd_rad_s": rate_sd, "gyro_bias_rad_s": gyro_bias, "gyro_gain": gain,
             "gyro_noise_rad_s": gyro_noise, "acc_noise_m_s2": acc_noise,
             "linear_acc_m_s2": lin_sd, "quaternion": q, "body_rate_rad_s": w,
             "scene": scene, "injected": scene.truth}
    return rec, truth


def simulate_null(samples=10000, seed=0, lsb=0.0, rate_hz=None, noise_scale=1.0, isotropic_noise=False):
    """(Recording, truth): a null recording of ``samples`` samples (see the module documentation).

    lsb: round the magnetometer to a multiple of this (uT; 0 = no rounding beyond float32; a
    rounded recording carries the library's quantization effect). rate_hz: the nominal output
    data rate (default: one of ODR_HZ at random). noise_scale: multiplies the drawn white noise
    (the other draws stay the same); isotropic_noise: every axis gets the RMS of the drawn
    per-axis levels. truth: the drawn platform and conventions."""
    rec, truth = simulate(samples, seed, lsb=lsb, rate_hz=rate_hz, noise_scale=noise_scale,
                          isotropic_noise=isotropic_noise)
    rec.meta["null"] = "no effect of the library"
    del truth["scene"], truth["injected"]
    return rec, truth


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lsb", type=float, default=0.0, help="round the magnetometer to this, uT (0: a null)")
    ap.add_argument("--rate", type=float, default=None, help="nominal output data rate, Hz (default: drawn)")
    ap.add_argument("--noise-scale", type=float, default=1.0, help="multiply the drawn white noise")
    ap.add_argument("--isotropic-noise", action="store_true", help="the same white noise on every axis")
    ap.add_argument("--session", choices=("flight", "hand"), default=None,
                    help="add throttle, current and voltage columns and a board temperature (no effect is injected)")
    ap.add_argument("--out", required=True, help="recording CSV to write (docs/spec/recording.md)")
    a = ap.parse_args(argv)
    try:
        if a.session:
            rec, truth = simulate(a.samples, a.seed, session=a.session, lsb=a.lsb, rate_hz=a.rate,
                                  noise_scale=a.noise_scale, isotropic_noise=a.isotropic_noise)
        else:
            rec, truth = simulate_null(a.samples, a.seed, a.lsb, a.rate, a.noise_scale, a.isotropic_noise)
    except ValueError as exc:
        ap.error(str(exc))
    rec.write(a.out)
    print(f"{a.out}: {len(rec)} samples at {1.0 / truth['period_s']:.4g} Hz, field {truth['field_uT']:.1f} uT, "
          f"noise {np.round(truth['noise_uT'], 3).tolist()} uT")
    return 0


if __name__ == "__main__":
    sys.exit(main())
