#!/usr/bin/env python
"""An independent simulator of null recordings: a magnetometer, accelerometer and gyroscope
with nothing the diagnosis lists as an effect.

    python tools/indep_sim.py --samples 10000 --seed 3 --out null.csv

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


def simulate_null(samples=10000, seed=0, lsb=0.0, rate_hz=None, noise_scale=1.0, isotropic_noise=False):
    """(Recording, truth): a null recording of ``samples`` samples (see the module documentation).

    lsb: round the magnetometer to a multiple of this (uT; 0 = no rounding beyond float32; a
    rounded recording carries the library's quantization effect). rate_hz: the nominal output
    data rate (default: one of ODR_HZ at random). noise_scale: multiplies the drawn white noise
    (the other draws stay the same); isotropic_noise: every axis gets the RMS of the drawn
    per-axis levels. truth: the drawn platform and conventions."""
    if samples < 10:
        raise ValueError(f"samples must be at least 10, got {samples}")
    if not (noise_scale >= 0 and math.isfinite(noise_scale)):
        raise ValueError(f"noise_scale must be a finite value >= 0, got {noise_scale}")
    if lsb < 0 or not math.isfinite(lsb):
        raise ValueError(f"lsb must be a finite value >= 0 uT, got {lsb}")
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

    mag = world_to_body(q, h_field) @ A.T + b + rng.normal(size=(samples, 3)) * sigma
    if lsb > 0:
        mag = np.round(mag / lsb) * lsb
    lin = ou_paths(rng, samples, dt, lin_tau, lin_sd, 3)
    acc = world_to_body(q, lin - np.array([0.0, 0.0, GRAVITY])) + rng.normal(0.0, acc_noise, (samples, 3))
    gyro = (w + gyro_bias) @ gain.T + rng.normal(0.0, gyro_noise, (samples, 3))
    rel = t - t[0]
    temp = (ambient + heat * (1.0 - np.exp(-rel / tau_heat)) + ou_paths(rng, samples, dt, 120.0, 0.3, 1)[:, 0])
    temp = np.round(temp / TEMP_RESOLUTION) * TEMP_RESOLUTION

    aux = {"ax": _f32(acc[:, 0]), "ay": _f32(acc[:, 1]), "az": _f32(acc[:, 2]),
           "gx": _f32(gyro[:, 0]), "gy": _f32(gyro[:, 1]), "gz": _f32(gyro[:, 2]), "temp": temp}
    meta = {"source": "tools/indep_sim.py", "units.mag": "uT", "units.acc": "m/s^2", "units.gyr": "rad/s",
            "rate_hz": f"{1.0 / dt:.6g}", "seed": str(seed), "null": "no effect of the library"}
    rec = Recording(t=t, mag=_f32(mag), aux=aux, meta=meta)
    truth = {"field_ned_uT": h_field, "field_uT": float(np.linalg.norm(h_field)), "soft_iron_map": A,
             "hard_iron_uT": b, "noise_uT": sigma, "lsb_uT": float(lsb), "period_s": dt, "odr_hz": odr,
             "rate_sd_rad_s": rate_sd, "gyro_bias_rad_s": gyro_bias, "gyro_gain": gain,
             "gyro_noise_rad_s": gyro_noise, "acc_noise_m_s2": acc_noise,
             "linear_acc_m_s2": lin_sd, "quaternion": q, "body_rate_rad_s": w}
    return rec, truth


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lsb", type=float, default=0.0, help="round the magnetometer to this, uT (0: a null)")
    ap.add_argument("--rate", type=float, default=None, help="nominal output data rate, Hz (default: drawn)")
    ap.add_argument("--noise-scale", type=float, default=1.0, help="multiply the drawn white noise")
    ap.add_argument("--isotropic-noise", action="store_true", help="the same white noise on every axis")
    ap.add_argument("--out", required=True, help="recording CSV to write (docs/spec/recording.md)")
    a = ap.parse_args(argv)
    try:
        rec, truth = simulate_null(a.samples, a.seed, a.lsb, a.rate, a.noise_scale, a.isotropic_noise)
    except ValueError as exc:
        ap.error(str(exc))
    rec.write(a.out)
    print(f"{a.out}: {len(rec)} samples at {1.0 / truth['period_s']:.4g} Hz, field {truth['field_uT']:.1f} uT, "
          f"noise {np.round(truth['noise_uT'], 3).tolist()} uT")
    return 0


if __name__ == "__main__":
    sys.exit(main())
