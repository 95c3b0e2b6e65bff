#!/usr/bin/env python
"""Blind benchmark of the sim-to-real gap diagnosis.

    python tools/blind_benchmark.py --trials 120 --out bench_blind --jobs 2

Three separate steps, so the diagnoser never sees a label:

1. ``generate``: recordings with no effect, one effect, two confusable ones, or one that is
   removed from the diagnoser's library, each written as a recording CSV with every aux column
   (temp, current, throttle, voltage, accelerometer, gyroscope) under ``OUT/recordings``; the
   labels (what was injected, how strongly) go to ``OUT/sealed/labels.json``. Effects are
   injected with forward models that differ from the library's own forms (a two-node thermal
   RC ladder, a wire pair's Biot-Savart field, tanh compression, a play-operator hysteresis,
   a first-order filter for latency, flicker noise, exponential relaxation ...), so the test is
   not circular. Each label also carries the trial's shape shares (tools/blind_shapes.py): how
   much of the injected change, noise-free, each wrong slow-offset form could follow.
2. ``run``: ``diagnose`` on every recording (only the recording, plus the library restriction
   of "removed" trials, which is part of the trial's setup, not of its label), results to
   ``OUT/results``.
3. ``score``: only now the labels are read; the acceptance figures are printed and written to
   ``OUT/score.json``.

``--step pool --runs DIR1 DIR2 ... --out OUT`` scores several runs as one (``OUT/pooled_score.json``):
a 90-trial plan has about 3 trials per effect, too few for a per-effect line.
``--step shapes`` adds the shape shares to a run generated before labels carried them (each trial
is regenerated from its seed and must match its recording on disk).
``--subset ci`` runs a small fixed subset; tests/test_diagnose_blind.py runs four of its trials (the null
and the removed step in CI, the single current and step with ``--runslow``).
``--simulator indep`` draws the trials from tools/indep_sim.py (a simulator written without
:mod:`mkc_stream.sim`) with the same effects, magnitudes and forward models
(tools/blind_indep.py adapts them); the default ``ours`` draws them from :mod:`mkc_stream.sim`.

Size: about 830 lines; generation, the oracle and scoring share the trial's conventions (effect
list, ranges, forward models, what counts as a miss), which one file keeps in step.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
if str(ROOT / "tools") not in sys.path:
    sys.path.insert(0, str(ROOT / "tools"))

from blind_shapes import SHAPE_CONFUSABLE, shape_shares  # noqa: E402
from mkc_stream.diagnose.forms import FORMS  # noqa: E402
from mkc_stream.sim import SensorModel, generate as make_trajectory, simulate  # noqa: E402
from mkc_stream.sim.effects.base import first_order_lag  # noqa: E402
from mkc_stream.sim.effects.noise import gauss_markov  # noqa: E402

DURATION, RATE = 500.0, 20.0          # 10^4 samples
SINGLE = ("temperature_offset", "temperature_scale", "current_hard_iron", "throttle_hard_iron",
          "hard_iron_drift", "hard_iron_step", "bias_random_walk", "scale_nonlinearity", "saturation",
          "higher_order_soft_iron", "quantization", "colored_noise", "latency", "timestamp_jitter",
          "sample_drops", "hysteresis", "misalignment")
PAIRS = ("temperature_offset|hard_iron_drift", "current_hard_iron|throttle_hard_iron",
         "cross_axis|misalignment", "colored_noise|bias_random_walk")
REMOVED = ("temperature_offset", "current_hard_iron", "hard_iron_step", "scale_nonlinearity", "hysteresis",
           "latency")
CI_SUBSET = [("none", None), ("single", "current_hard_iron"), ("single", "hard_iron_step"),
             ("single", "temperature_offset"), ("single", "saturation"), ("pair", "cross_axis|misalignment"),
             ("removed", "hard_iron_step")]


#: Magnitudes drawn (log-uniform) for the effects whose realistic range the issue gives: the
#: whole range, bottom included. Trials an oracle could not see are scored apart (ORACLE_SNR).
#: current_hard_iron: the distance (m) of a 5 mm wire pair, i.e. 0.5-0.005 uT/A.
RANGES = {"temperature_offset": (1.0, 50.0),         # nT/degC
          "temperature_scale": (0.005, 0.3),         # %/degC
          "current_hard_iron": (0.045, 0.45),        # m (0.5-0.005 uT/A)
          "hard_iron_drift": (0.01, 1.0),            # uT/h, mean over the recording
          "scale_nonlinearity": (10.0, 500.0)}       # nT at 50 uT
#: A trial is "typical" (counted in the named-first lines) unless an oracle that knows the
#: injected signal exactly up to its amplitude could not detect it: a one-parameter matched
#: filter on the norm and dip channels (after what the ellipsoid and dip refit absorb) with
#: each channel's simulated noise (the dip channel's includes the accelerometer's direction
#: error, whitened by its spectrum: see oracle_snr) detects at 1% false alarm with 90% power only when its
#: signal-to-noise ratio is at least z_0.99 + z_0.90 = 2.33 + 1.28 = 3.6. Below that, no
#: diagnoser could name the effect reliably from 10^4 samples; those trials are listed and
#: counted separately (with the magnitude at which the oracle would reach 3.6), not dropped.
ORACLE_SNR = 3.6


def loguniform(rng, lo, hi):
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def random_direction(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


class Inject:
    """A custom forward model for the simulator (stage + apply)."""

    def __init__(self, name, stage, fn):
        self.name, self.stage, self.fn = name, stage, fn

    def apply(self, ctx, params):
        self.fn(ctx)


def rc_ladder(t, T_board, taus):
    """Die temperature behind the board sensor: a three-node thermal RC ladder (each node
    exchanges heat with both neighbours, unlike a cascade of independent lags), integrated
    with small explicit steps."""
    ta, tb, tc = taus
    T = np.full(3, T_board[0])
    out = np.empty_like(T_board)
    for k in range(len(t)):
        dt = (t[k] - t[k - 1]) if k else 0.0
        n = max(1, int(np.ceil(dt / (0.2 * min(taus)))))
        h = dt / n
        for _ in range(n):
            d1 = (T_board[k] - T[0]) / ta + (T[1] - T[0]) / tb
            d2 = (T[0] - T[1]) / tb + (T[2] - T[1]) / tc
            d3 = (T[1] - T[2]) / tc
            T = T + h * np.array([d1, d2, d3])
        out[k] = T[2]
    return out


def wire_pair_field(rng, r_lo=0.07, r_hi=0.20, spacing=0.005):
    """Field per ampere (uT/A) at the sensor of a supply/return wire pair (Biot-Savart)."""
    mu0_2pi = 0.2                                      # uT m / A
    d = random_direction(rng)                          # wire direction
    r = rng.uniform(r_lo, r_hi)
    perp = np.cross(d, random_direction(rng))
    perp /= np.linalg.norm(perp)
    sep = np.cross(d, perp)
    B = np.zeros(3)
    for sign, off in ((1.0, 0.5 * spacing), (-1.0, -0.5 * spacing)):
        rv = r * perp + off * sep                      # from the wire to the sensor, perpendicular to it
        B += sign * mu0_2pi * np.cross(d, rv) / (rv @ rv)
    return B


def make_injection(name, rng, traj, sensor):
    """(custom effect objects, truth dict) for one effect."""
    t = traj.t
    T = t[-1] - t[0]
    if name == "temperature_offset":
        c = random_direction(rng) * loguniform(rng, *RANGES[name])       # nT/degC
        Td = rc_ladder(t, traj.aux["temp"], rng.uniform(5, 30, 3)) - 25.0
        curv = rng.uniform(-0.004, 0.004)                               # slight curvature, 1/degC

        def fn(ctx):
            ctx.m += np.outer(Td + curv * Td ** 2, c * 1e-3)
        return [Inject(name, "offset", fn)], {"value": float(np.linalg.norm(c)), "unit": "nT/degC"}
    if name == "temperature_scale":
        a = np.abs(rng.normal(size=3)) * 0.5 + 0.5
        a = a / np.linalg.norm(a) * loguniform(rng, *RANGES[name])     # %/degC
        Td = rc_ladder(t, traj.aux["temp"], rng.uniform(5, 30, 3)) - 25.0

        def fn(ctx):
            ctx.m += (ctx.m - ctx.b) * np.outer(Td, a * 1e-2)
        return [Inject(name, "sensor", fn)], {"value": float(np.linalg.norm(a)), "unit": "%/degC"}
    if name == "current_hard_iron":
        # the wire pair 4.5-45 cm away: 0.5-0.005 uT/A, the realistic range
        k = wire_pair_field(rng, *RANGES[name])
        return [Inject(name, "offset", lambda ctx: ctx.m.__iadd__(np.outer(traj.aux["current"] - 0.0, k)))], \
            {"value": float(np.linalg.norm(k)), "unit": "uT/A"}
    if name == "throttle_hard_iron":
        full = random_direction(rng) * loguniform(rng, 0.3, 3.0)       # uT at full throttle
        thr = first_order_lag(t, np.clip(traj.aux["throttle"], 0, 1), 0.2)   # ESC and motor respond with a lag
        return [Inject(name, "offset", lambda ctx: ctx.m.__iadd__(np.outer(thr ** 1.5, full)))], \
            {"value": float(np.linalg.norm(full)), "unit": "uT"}
    if name == "hard_iron_drift":
        mean = loguniform(rng, *RANGES[name])                            # uT/h over the recording
        tau = rng.uniform(1.0, 3.0) * T
        x = 1.0 - np.exp(-(t - t[0]) / tau)                              # exponential relaxation
        d = random_direction(rng) * mean / 3600.0 * T / x[-1]
        mean_rate = float(np.linalg.norm(d) * x[-1] / T * 3600.0)
        return [Inject(name, "offset", lambda ctx: ctx.m.__iadd__(np.outer(x, d)))], \
            {"value": mean_rate, "unit": "uT/h"}
    if name == "hard_iron_step":
        delta = random_direction(rng) * loguniform(rng, 0.2, 1.5)
        t0 = t[0] + rng.uniform(0.15, 0.85) * T
        width = rng.uniform(0.3, 2.0)
        x = 1.0 / (1.0 + np.exp(-(t - t0) / width))
        return [Inject(name, "offset", lambda ctx: ctx.m.__iadd__(np.outer(x, delta)))], \
            {"value": float(np.linalg.norm(delta)), "unit": "uT", "t_step": float(t0 - t[0])}
    if name == "bias_random_walk":
        q = loguniform(rng, 0.4, 1.5)                                    # uT/sqrt(h)
        tc = np.arange(t[0], t[-1] + 1.0, 1.0)
        w = np.cumsum(rng.normal(size=(tc.size, 3)), axis=0) * q / 60.0
        walk = np.stack([np.interp(t, tc, w[:, j]) for j in range(3)], axis=1)
        return [Inject(name, "offset", lambda ctx: ctx.m.__iadd__(walk))], {"value": q, "unit": "uT/sqrt(h)"}
    if name == "scale_nonlinearity":
        beta = loguniform(rng, *RANGES[name]) * (0.5 + rng.uniform(size=3)) / np.sqrt(3)   # nT at 50 uT
        L = np.sqrt(50.0 ** 3 / (3.0 * beta * 1e-3))
        dep = 50.0 - L * np.tanh(50.0 / L)

        def fn(ctx):
            x = ctx.m - ctx.b
            ctx.m[:] = ctx.b + L * np.tanh(x / L)
        return [Inject(name, "sensor", fn)], {"value": float(np.linalg.norm(dep) * 1e3), "unit": "nT"}
    if name == "saturation":
        def fn(ctx):
            j = int(np.argmax(np.ptp(ctx.m, axis=0)))
            level = float(np.percentile(ctx.m[:, j], 100 - rng.uniform(2.0, 5.0)))
            ctx.truth["level"] = level
            np.minimum(ctx.m[:, j], level, out=ctx.m[:, j])
        return [Inject(name, "range", fn)], {"value": None, "unit": "uT", "from_ctx": "level"}
    if name == "higher_order_soft_iron":
        # three saturating "rods" of soft iron along random directions: dm = sum a_k (n_k.B)^2 / 50 uT
        rods = [(random_direction(rng), random_direction(rng)) for _ in range(3)]
        amp = loguniform(rng, 0.1, 0.4)                                # uT, observable RMS at 50 uT
        from mkc_stream.diagnose.forms import norm_pattern_rms

        def raw(B):
            return sum(np.outer((B @ n) ** 2 / 50.0, a) for n, a in rods)
        scale = amp / norm_pattern_rms(lambda u: raw(50.0 * u))
        return [Inject(name, "offset", lambda ctx: ctx.m.__iadd__(scale * raw(ctx.B)))], \
            {"value": amp, "unit": "uT"}
    if name == "quantization":
        lsb = float(np.mean(np.atleast_1d(sensor.noise))) * rng.uniform(1.0, 4.0)
        off = rng.uniform(0, lsb)

        def fn(ctx):
            ctx.m[:] = (np.floor((ctx.m - off) / lsb) + 0.5) * lsb + off    # a mid-rise quantizer
        return [Inject(name, "range", fn)], {"value": lsb, "unit": "uT"}
    if name == "colored_noise":
        sig = loguniform(rng, 0.05, 0.2)
        taus = (0.5, 5.0, 30.0)
        noise = sum(gauss_markov(rng, t, sig / np.sqrt(3), tau) for tau in taus)   # flicker-like
        return [Inject(name, "noise", lambda ctx: ctx.m.__iadd__(noise))], {"value": sig, "unit": "uT"}
    if name == "latency":
        lat = loguniform(rng, 5.0, 40.0)                                 # ms, the latency the filter adds
        dt = 1.0 / RATE
        tau = -dt / np.log(lat / (lat + dt * 1e3)) * 1e3                  # ms, its time constant

        def fn(ctx):
            for j in range(3):
                ctx.B[:, j] = first_order_lag(ctx.t, ctx.B[:, j], tau * 1e-3)
        # the sampled filter y_k = y_k-1 + (1 - a)(x_k - y_k-1), a = exp(-dt/tau), delays slow
        # signals by a / (1 - a) samples: that, not tau, is the latency it adds
        return [Inject(name, "field", fn)], {"value": float(lat), "unit": "ms"}
    if name == "timestamp_jitter":
        mu = loguniform(rng, 0.5, 4.0)                                   # ms, mean = sd of an exponential delay

        def fn(ctx):
            ctx.t_out[:] = np.maximum.accumulate(ctx.t_out + rng.exponential(mu * 1e-3, ctx.n))
        return [Inject(name, "clock", fn)], {"value": mu, "unit": "ms"}
    if name == "sample_drops":
        frac = rng.uniform(0.01, 0.05)

        def fn(ctx):
            lost, n = 0, ctx.n
            while lost < frac * n:
                s = int(rng.integers(1, n - 1))
                L = int(rng.geometric(1 / 3.0))
                lost += int(ctx.keep[s:s + L].sum())
                ctx.keep[s:s + L] = False
        return [Inject(name, "clock", fn)], {"value": frac, "unit": "fraction"}
    if name == "hysteresis":
        a = loguniform(rng, 0.08, 0.3)

        def fn(ctx):
            x = ctx.m - ctx.b
            y = np.empty_like(x)
            y[0] = x[0]
            for k in range(1, ctx.n):                               # play operator, half-width a
                y[k] = np.clip(y[k - 1], x[k] - a, x[k] + a)
            ctx.m[:] = ctx.b + y
        return [Inject(name, "sensor", fn)], {"value": a, "unit": "uT"}
    if name in ("misalignment", "cross_axis"):
        ang = loguniform(rng, 0.7, 3.0)
        if name == "misalignment":
            R = Rotation.from_rotvec(np.radians(ang) * random_direction(rng)).as_matrix()
            return [Inject(name, "field", lambda ctx: ctx.B.__setitem__(slice(None), ctx.B @ R.T))], \
                {"value": ang, "unit": "deg"}
        K = np.radians(ang) * rng.normal(size=(3, 3)) / 1.5
        np.fill_diagonal(K, 0.0)
        rot = float(np.degrees(np.linalg.norm([K[2, 1] - K[1, 2], K[0, 2] - K[2, 0], K[1, 0] - K[0, 1]]) / 2))
        return [Inject(name, "field", lambda ctx: ctx.B.__setitem__(slice(None), ctx.B @ (np.eye(3) + K).T))], \
            {"value": rot, "unit": "deg"}
    raise ValueError(name)


def whitener(coloured, white, half_width=16):
    """A linear map z -> y with sum(y^2) = sum_k |Z_k|^2 / (N P_k) (Parseval), P_k the noise's
    spectral density: the coloured draw's periodogram smoothed over 2 half_width + 1 bins,
    plus white^2. Applied to a signal and to the nuisance columns alike, it turns the Gaussian
    noise white, so least squares on the mapped vectors is the whitened (GLS) fit."""
    n = coloured.size
    per = np.abs(np.fft.fft(coloured)) ** 2 / n
    P = uniform_filter1d(per, 2 * half_width + 1, mode="wrap") + white ** 2
    return lambda z: np.real(np.fft.ifft(np.fft.fft(z) / np.sqrt(P)))


def matched_snr2(signal, coloured, white, half_width=16):
    """SNR^2 of a known signal in Gaussian noise = a coloured series (one draw of it) plus white
    noise: that of the whitened (GLS) matched filter; for white noise alone sum(signal^2) /
    white^2."""
    y = whitener(coloured, white, half_width)(signal)
    return float(y @ y)


#: Effects with an oracle SNR: those whose injected change is a deterministic function of the
#: trajectory, aux signals and magnitude, with samples that line up (no clock effect). Noise
#: processes (a coloured noise, a random walk, a quantizer's error) have no fixed shape to know.
ORACLE_EFFECTS = {"temperature_offset", "temperature_scale", "current_hard_iron", "throttle_hard_iron",
                  "hard_iron_drift", "hard_iron_step", "scale_nonlinearity", "saturation", "cross_axis",
                  "higher_order_soft_iron", "latency", "hysteresis", "misalignment"}


def calibration_nuisance(x, S):
    """(9, N, 3): calibrated-frame changes of the baseline's 9 calibration parameters (hard
    iron b: 3, a symmetric perturbation of S: 6) at the raw minus hard iron x. F and dip0 act
    on one channel each; the caller adds them."""
    n = x.shape[0]
    out = [np.tile(S[:, k], (n, 1)) for k in range(3)]       # d(S (m - b)) / db_k, sign aside
    for i in range(3):
        for j in range(i, 3):
            Ex = np.zeros((n, 3))
            Ex[:, i] += x[:, j]
            if i != j:
                Ex[:, j] += x[:, i]
            out.append(Ex)                                       # E_ij x, E_ij symmetric
    return np.stack(out)


def oracle_snr(sim, clean, traj, sensor):
    """Signal-to-noise ratio of the injected change for an oracle that knows its exact shape
    (everything but its amplitude): the change of the raw signal (same noise draws with and
    without the effect) seen in the norm channel and in the dip against gravity, minus what the
    refitted calibration absorbs, over each channel's simulated noise. Clock-free effects only
    (the samples line up).

    The calibration is refitted on both channels at once (as the diagnoser's baseline is):
    hard iron, symmetric soft iron, the field F (norm) and the dip dip0 (dip). So a change
    that is part symmetric soft iron (a cross-axis coupling's symmetric part) counts only with
    what is left of it in both channels, not with its direction change alone.

    Noise: the norm channel has the magnetometer's white noise. The dip channel measures the
    field's direction against the accelerometer's, so it also has the accelerometer's
    direction error (linear acceleration and noise: about 1.7 deg RMS on the generated
    trajectories, 10-30 times the magnetometer's own, correlated over ~0.5 s). The oracle
    whitens it with its spectrum, taken from the clean simulation (:func:`whitener`), and
    the fit is the joint GLS projection of the signal off the calibration's columns."""
    d = sim.mag_full - clean.mag_full
    ctx = clean.ctx
    S = ctx.S
    x = ctx.B @ np.linalg.inv(S).T                                  # noise-free raw minus hard iron
    v = ctx.B / np.linalg.norm(ctx.B, axis=1, keepdims=True)
    p = d @ S.T                                                      # calibrated-frame change
    nuis = calibration_nuisance(x, S)
    noise = float(np.mean(np.atleast_1d(sensor.noise)))
    n = len(v)
    # per channel, in units of its noise: the calibration's columns (b, S, F, dip0) and the
    # signal; norm channel: v . change, F shifts it by a constant
    blocks = [np.concatenate([np.einsum("nk,cnk->cn", v, nuis), np.ones((1, n)), np.zeros((1, n))]) / noise]
    y = [np.sum(v * p, axis=1) / noise]
    if traj.acc is not None:
        g = traj.acc / np.linalg.norm(traj.acc, axis=1, keepdims=True)
        w = g - np.sum(g * v, axis=1, keepdims=True) * v
        w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-9)
        acc = np.stack([clean.recording.aux[c] for c in ("ax", "ay", "az")], axis=1)
        gm = acc / np.linalg.norm(acc, axis=1, keepdims=True)
        dip = np.arccos(np.clip(np.sum(gm * v, axis=1), -1.0, 1.0))    # measured dip (true field)
        wh = whitener(np.mean(np.linalg.norm(ctx.B, axis=1)) * (dip - dip.mean()), noise)
        # dip channel (|B| times the angle, uT): w . change; dip0 shifts it by a constant
        blocks.append(np.stack([wh(c) for c in np.einsum("nk,cnk->cn", w, nuis)] + [np.zeros(n), wh(np.ones(n))]))
        y.append(wh(np.sum(w * p, axis=1)))
    A = np.concatenate(blocks, axis=1).T
    yy = np.concatenate(y)
    r = yy - A @ np.linalg.lstsq(A, yy, rcond=None)[0]
    return float(np.sqrt(r @ r))


def trial_effects(kind, truth, rng, traj, sensor):
    """(custom effect objects, magnitude) of a trial's injected effect: a pair's coloured noise
    is slower (40-80 s) than the single effect's, to be confusable with a random walk."""
    if truth == "colored_noise" and kind == "pair":
        sig = loguniform(rng, 0.1, 0.3)
        tau = rng.uniform(40.0, 80.0)
        noise = gauss_markov(rng, traj.t, sig, tau)
        return [Inject(truth, "noise", lambda ctx: ctx.m.__iadd__(noise))], {"value": sig, "unit": "uT"}
    return make_injection(truth, rng, traj, sensor)


def make_trial(kind, effect, seed, simulator="ours"):
    """One recording and its label; simulator "indep": from tools/indep_sim.py (tools/blind_indep.py)."""
    if simulator == "indep":
        if str(ROOT / "tools") not in sys.path:
            sys.path.insert(0, str(ROOT / "tools"))
        from blind_indep import make_indep_trial

        return make_indep_trial(kind, effect, seed, sys.modules[__name__])
    if simulator != "ours":
        raise ValueError(f"unknown simulator {simulator!r}; use ours or indep")
    rng = np.random.default_rng(seed)
    other_loads, temp = True, "cycle"
    truth = effect
    if kind == "pair":
        truth, _ = effect.split("|")
        if truth == "temperature_offset":
            temp = "ramp"
        if truth == "current_hard_iron":
            other_loads = False
    traj = make_trajectory("hand" if rng.uniform() < 0.7 else "figure8", duration=DURATION, rate=RATE, seed=seed,
                           temp=temp, power=True, other_loads=other_loads, temp_amplitude=rng.uniform(6, 12),
                           temp_cycles=rng.uniform(3, 6))
    from mkc_stream.calib.synthetic import random_soft_iron

    sensor = SensorModel(field=rng.uniform(25.0, 65.0), hard_iron=tuple(rng.uniform(-30, 30, 3)),
                         soft_iron=random_soft_iron(rng, 0.15), noise=rng.uniform(0.05, 0.15),
                         burst_fraction=float(rng.choice([0.0, 0.01, 0.03])))
    effects, label = [], {"kind": kind, "truth": None, "pair": None, "magnitude": None}
    if truth is not None:
        effects, mag = trial_effects(kind, truth, rng, traj, sensor)
        label.update(truth=truth, magnitude=mag, pair=effect.split("|") if kind == "pair" else None)
    sim = simulate(traj, sensor, effects=[(e, {}) for e in effects], seed=seed + 1)
    if truth is not None:
        clean = simulate(traj, sensor, seed=seed + 1)                  # the same draws, no effect
        if truth in ORACLE_EFFECTS:
            label["oracle_snr"] = oracle_snr(sim, clean, traj, sensor)
        label["shape_share"] = shape_shares(sim.recording.t, sim.recording.aux, sim.mag_full - clean.mag_full)
    if label["magnitude"] and label["magnitude"].get("from_ctx"):
        label["magnitude"]["value"] = float(sim.truth[label["magnitude"].pop("from_ctx")])
    label["exclude"] = [truth] if kind == "removed" else []
    return sim.recording, label


def trial_plan(n, seed):
    """A fixed mix: 15% no effect, 60% single (cycling through the effects), 12% pairs, 13% removed."""
    n_none = max(1, round(0.15 * n))
    n_pair = max(1, round(0.12 * n))
    n_rem = max(1, round(0.13 * n))
    n_single = max(1, n - n_none - n_pair - n_rem)
    plan = [("none", None)] * n_none
    plan += [("single", SINGLE[i % len(SINGLE)]) for i in range(n_single)]
    plan += [("pair", PAIRS[i % len(PAIRS)]) for i in range(n_pair)]
    plan += [("removed", REMOVED[i % len(REMOVED)]) for i in range(n_rem)]
    return [(k, e, seed * 100_003 + i) for i, (k, e) in enumerate(plan)]


def select(plan, only=None, index=None):
    """(plan index, trial) pairs of a subset: ``only`` effect names (a trial is kept when its
    effect, or one of its pair, is named; "none" names the no-effect trials), ``index`` plan
    positions ("3,7,10-12"). Trials keep their plan position in their name, so a subset's
    results line up with the full run's."""
    idx = set()
    for part in (index or "").split(","):
        if part.strip():
            a, _, b = part.partition("-")
            idx.update(range(int(a), int(b or a) + 1))
    names = {x.strip() for x in (only or "").split(",") if x.strip()}
    out = []
    for i, (kind, effect, seed) in enumerate(plan):
        if idx and i not in idx:
            continue
        if names and not ((effect is None and "none" in names)
                          or (effect is not None and names & set(effect.split("|")))):
            continue
        out.append((i, (kind, effect, seed)))
    return out


def step_generate(out, plan, simulator="ours"):
    """plan: (kind, effect, seed) tuples, or (plan index, tuple) pairs from :func:`select`;
    simulator: "ours" (mkc_stream.sim) or "indep" (tools/indep_sim.py)."""
    rec_dir, sealed = out / "recordings", out / "sealed"
    rec_dir.mkdir(parents=True, exist_ok=True)
    sealed.mkdir(parents=True, exist_ok=True)
    labels = {}
    for i, item in enumerate(plan):
        if isinstance(item[1], tuple):
            i, item = item
        kind, effect, seed = item
        rec, label = make_trial(kind, effect, seed, simulator)
        name = f"trial{i:04d}"
        rec.write(rec_dir / f"{name}.csv")
        # the library restriction is the trial's setup (what the diagnoser is given), not its label
        (rec_dir / f"{name}.setup.json").write_text(json.dumps({"exclude": label["exclude"]}))
        labels[name] = {**label, "seed": seed}
    (sealed / "labels.json").write_text(json.dumps(labels, indent=1))
    return sorted(labels)


def step_shapes(out, plan, simulator="ours"):
    """Adds each trial's shape shares (tools/blind_shapes.py) to the sealed labels of a run
    generated before labels carried them. Each trial is regenerated from its seed and must be the
    recording on disk (else the generator has changed since, and the run cannot be relabelled)."""
    from mkc_stream.io.recording import read_recording

    path = out / "sealed" / "labels.json"
    labels = json.loads(path.read_text())
    done = 0
    for i, item in enumerate(plan):
        if isinstance(item[1], tuple):
            i, item = item
        kind, effect, seed = item
        name = f"trial{i:04d}"
        if name not in labels:
            continue
        if labels[name]["seed"] != seed:
            raise SystemExit(f"{name}: seed {labels[name]['seed']} on disk, {seed} in this plan (other --trials/--seed?)")
        rec, label = make_trial(kind, effect, seed, simulator)
        disk = read_recording(out / "recordings" / f"{name}.csv")
        if disk.mag.shape != rec.mag.shape or not np.allclose(disk.mag, rec.mag, rtol=0.0, atol=1e-5):
            raise SystemExit(f"{name}: the regenerated recording differs from the one on disk "
                             f"(the generator changed since the run); its labels are left as they were")
        if "shape_share" in label:
            labels[name]["shape_share"] = label["shape_share"]
            done += 1
        print(f"  {name}: {len(label.get('shape_share') or {})} shares", flush=True)
    path.write_text(json.dumps(labels, indent=1))
    print(f"shape shares added to {done} of {len(labels)} labels in {path}")


def _diagnose_one(args):
    path, out_dir = args
    from mkc_stream.diagnose import diagnose
    from mkc_stream.io.recording import read_recording

    setup = json.loads(pathlib.Path(str(path).replace(".csv", ".setup.json")).read_text())
    t0 = time.perf_counter()
    d = diagnose(read_recording(path), exclude=setup["exclude"])
    obj = d.to_json()
    obj["seconds"] = time.perf_counter() - t0
    (out_dir / (path.stem + ".json")).write_text(json.dumps(obj))
    return path.stem, obj["verdict"], obj["seconds"]


def step_run(out, jobs=1):
    res = out / "results"
    res.mkdir(parents=True, exist_ok=True)
    paths = sorted((out / "recordings").glob("trial*.csv"))
    todo = [(p, res) for p in paths if not (res / (p.stem + ".json")).exists()]
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(jobs) as pool:
            for name, verdict, sec in pool.imap_unordered(_diagnose_one, todo):
                print(f"  {name}: {verdict} ({sec:.1f} s)", flush=True)
    else:
        for item in todo:
            name, verdict, sec = _diagnose_one(item)
            print(f"  {name}: {verdict} ({sec:.1f} s)", flush=True)


ALIASES = {"cross_axis": {"misalignment"}, "misalignment": {"cross_axis"}}
CATCH_ALL = {"bias_random_walk", "colored_noise"}
#: each effect's partners in the confusable pairs the benchmark declares (PAIRS)
PARTNERS = {}
for _pair in PAIRS:
    _a, _b = _pair.split("|")
    PARTNERS.setdefault(_a, set()).add(_b)
    PARTNERS.setdefault(_b, set()).add(_a)


#: each effect's containers: the forms that hold it as a special case (``MeanForm.contains``, the
#: diagnoser's own declaration: sensor_compression's odd cubic terms are scale_nonlinearity's
#: columns), which close whatever it closes; the lines "outside the declared pair" leave them out
CONTAINERS = {}
for _name, _form in FORMS.items():
    for _inner in getattr(_form, "contains", ()):
        CONTAINERS.setdefault(_inner, set()).add(_name)


def declared(truth):
    """The wrong effects the truth's lines "outside the declared pair" leave out: its partners in
    PAIRS and the forms that contain it."""
    return PARTNERS.get(truth, set()) | CONTAINERS.get(truth, set())


def wrong_source(truth, name):
    """Why a wrong effect can close the gap: a catch-all noise model (widens its replicas), the
    truth's declared confusable partner (PAIRS), a form containing the truth, or another effect."""
    if name in CATCH_ALL:
        return "catch_all"
    if name in CONTAINERS.get(truth, set()):
        return "contains_truth"
    return "declared_partner" if name in PARTNERS.get(truth, set()) else "other"


def frac(flags):
    return float(np.mean(flags)) if len(flags) else None


def named_first(row):
    """The truth is the first effect the diagnosis selected."""
    return bool(row["selected"]) and row["selected"][0] == row["truth"]


def named_first_or_ambiguous(row):
    """The truth is selected first or listed among the effects the diagnosis cannot rank."""
    return row["truth"] in (row["selected"][:1] + row["ambiguous"])


def named_first_per_effect(rows):
    """{truth: share of its rows named first}."""
    per = {}
    for r in rows:
        per.setdefault(r["truth"], []).append(named_first(r))
    return {k: float(np.mean(v)) for k, v in sorted(per.items())}


def share_le(rows, key, limit=0.3):
    """Share of the rows whose ``key`` (a best-wrong shrink) is at most limit; rows without one
    (no wrong effect of that kind was scored) are left out."""
    vals = [r[key] for r in rows if r.get(key) is not None]
    return frac([v <= limit for v in vals])


def step_score(out):
    """Score one run: (summary, rows), also written to ``OUT/score.json``."""
    rows = score_rows(out)
    S = summarise(rows)
    (out / "score.json").write_text(json.dumps({"summary": S, "rows": rows}, indent=1))
    return S, rows


def step_pool(runs, out):
    """Score several runs as one (plans of either simulator, other seeds): (summary, rows), also
    written to ``OUT/pooled_score.json``. A plan of 90 trials holds 3 or so trials per effect and
    7-10 pairs and removed effects, where one trial moves a line by 10-33 points; pooled, the lines
    rest on enough trials (``summary["counts"]`` says how many). Each row's trial name is prefixed
    with its run's directory name."""
    rows = []
    for run in runs:
        run = pathlib.Path(run)
        rows += [{**r, "trial": f"{run.name}/{r['trial']}"} for r in score_rows(run)]
    S = summarise(rows)
    S["runs"] = [str(r) for r in runs]
    out.mkdir(parents=True, exist_ok=True)
    (out / "pooled_score.json").write_text(json.dumps({"summary": S, "rows": rows}, indent=1))
    return S, rows


def score_rows(out):
    """One row per trial of a run: its label and its diagnosis side by side (labels read here)."""
    labels = json.loads((out / "sealed" / "labels.json").read_text())
    rows = []
    for name, lab in sorted(labels.items()):
        path = out / "results" / f"{name}.json"
        if not path.is_file():
            raise ValueError(f"{out}: trial {name} has no result (its diagnosis has not run: --step run)")
        r = json.loads(path.read_text())
        eff = {e["name"]: e for e in r["effects"]}
        truth = lab["truth"]
        row = {"trial": name, "kind": lab["kind"], "truth": truth, "verdict": r["verdict"],
               "selected": r["selected"], "ambiguous": r["ambiguous_with"], "seconds": r["seconds"],
               "has_shape_share": "shape_share" in lab}
        snr = lab.get("oracle_snr")
        row["oracle_snr"] = snr
        row["typical"] = snr is None or snr >= ORACLE_SNR
        if truth:
            row["mag_true"] = lab["magnitude"]["value"]
        if truth and truth in eff:
            e = eff[truth]
            row["shrink_truth"] = e["shrink"]
            row["mag_est"] = (e.get("magnitude") or {}).get("value")
        wrong = [e for n, e in eff.items()
                 if n != truth and n not in ALIASES.get(truth, set()) and e["shrink"] is not None]
        row["best_wrong"] = max([e["shrink"] for e in wrong], default=None)
        if wrong:
            top = max(wrong, key=lambda e: e["shrink"])
            row["best_wrong_name"] = top["name"]
            row["best_wrong_source"] = wrong_source(truth, top["name"])
        unpaired = [e for e in wrong if e["name"] not in declared(truth)]
        row["best_wrong_unpaired"] = max([e["shrink"] for e in unpaired], default=None)
        row["best_wrong_unpaired_det"] = max([e["shrink"] for e in unpaired if e["name"] not in CATCH_ALL],
                                             default=None)
        row["best_wrong_det"] = max([e["shrink"] for e in wrong if e["name"] not in CATCH_ALL], default=None)
        # the same, leaving out too the wrong forms that follow >= SHAPE_CONFUSABLE of the truth's
        # noise-free change (tools/blind_shapes.py); None for a run generated without the shares
        shares = lab.get("shape_share")
        row["wrong_shape_confusable"] = sorted(n for n, v in (shares or {}).items()
                                               if n != truth and v >= SHAPE_CONFUSABLE)
        row["best_wrong_shape_separable_det"] = None if shares is None else max(
            [e["shrink"] for e in unpaired if e["name"] not in CATCH_ALL
             and shares.get(e["name"], 0.0) < SHAPE_CONFUSABLE], default=None)
        row["best_wrong_given"] = max([e.get("shrink_given_selected") or 0.0 for e in wrong], default=None)
        rows.append(row)
    return rows


def summarise(rows):
    """The acceptance figures over rows of :func:`score_rows` (one run's, or several pooled)."""
    S = {}
    none = [r for r in rows if r["kind"] == "none"]
    S["false_alarm_rate"] = float(np.mean([r["verdict"] != "no_gap" for r in none])) if none else None
    single_all = [r for r in rows if r["kind"] == "single"]
    # the named-first lines are over trials at typical magnitudes: those an oracle could see
    # (ORACLE_SNR); the ones below are reported here, not dropped
    single = [r for r in single_all if r["typical"]]
    below = [r for r in single_all if not r["typical"]]
    S["single_trials"], S["single_below_oracle"] = len(single_all), len(below)
    S["named_first_all_magnitudes"] = frac([named_first(r) for r in single_all])
    S["below_oracle"] = {}
    for r in below:
        e = S["below_oracle"].setdefault(r["truth"], {"trials": 0, "detected": 0, "magnitudes": [],
                                                      "oracle_threshold": []})
        e["trials"] += 1
        e["detected"] += int(r["verdict"] != "no_gap")
        e["magnitudes"].append(r["mag_true"])
        e["oracle_threshold"].append(r["mag_true"] * ORACLE_SNR / max(r["oracle_snr"], 1e-12))
    thr = {}
    for r in single_all:
        if r.get("oracle_snr"):
            thr.setdefault(r["truth"], []).append(r["mag_true"] * ORACLE_SNR / r["oracle_snr"])
    S["oracle_threshold_median"] = {k: float(np.median(v)) for k, v in sorted(thr.items())}
    S["single_detected"] = float(np.mean([r["verdict"] != "no_gap" for r in single])) if single else None
    S["named_first"] = frac([named_first(r) for r in single])
    S["named_first_per_effect"] = named_first_per_effect(single)
    S["named_first_or_ambiguous"] = frac([named_first_or_ambiguous(r) for r in single])
    # the same lines split by the shapes (docs/decisions/0033): on the trials where no wrong
    # slow-offset form follows SHAPE_CONFUSABLE of the truth's noise-free change, the recording
    # holds what ranks the truth first; on the others it may not, and the report can only list
    # the truth among the forms it cannot rank (runs generated without the shares are left out)
    shaped = [r for r in single if r["has_shape_share"]]
    separable = [r for r in shaped if not r["wrong_shape_confusable"]]
    confusable = [r for r in shaped if r["wrong_shape_confusable"]]
    S["shape_separable_trials"], S["shape_confusable_trials"] = len(separable), len(confusable)
    S["named_first_shape_separable"] = frac([named_first(r) for r in separable])
    S["named_first_per_effect_shape_separable"] = named_first_per_effect(separable)
    S["named_first_shape_confusable"] = frac([named_first(r) for r in confusable])
    S["named_first_or_ambiguous_shape_confusable"] = frac([named_first_or_ambiguous(r) for r in confusable])
    det = [r for r in single if r["verdict"] != "no_gap"]
    sh = [r.get("shrink_truth") for r in det]
    S["shrink_correct_ge_0.7"] = float(np.mean([s is not None and s >= 0.7 for s in sh])) if det else None
    S["shrink_correct_median"] = float(np.median([s for s in sh if s is not None])) if det else None
    bw = [r["best_wrong"] for r in det if r["best_wrong"] is not None]
    S["best_wrong_le_0.3"] = share_le(det, "best_wrong")
    S["best_wrong_median"] = float(np.median(bw)) if bw else None
    # what the failures of that line are made of (the wrong effect closing the most of each one)
    src = {}
    for r in det:
        if r["best_wrong"] is not None and r["best_wrong"] > 0.3:
            src[r["best_wrong_source"]] = src.get(r["best_wrong_source"], 0) + 1
    S["best_wrong_over_0.3_by_source"] = dict(sorted(src.items()))
    S["best_wrong_without_declared_partner_le_0.3"] = share_le(det, "best_wrong_unpaired")
    S["best_wrong_deterministic_without_declared_partner_le_0.3"] = share_le(det, "best_wrong_unpaired_det")
    S["best_wrong_deterministic_le_0.3"] = share_le(det, "best_wrong_det")
    S["best_wrong_deterministic_shape_separable_le_0.3"] = share_le(det, "best_wrong_shape_separable_det")
    # the failures of the line outside the declared pair whose wrong effect shares the truth's shape
    S["best_wrong_over_0.3_shape_confusable"] = sum(
        1 for r in det if (r["best_wrong_unpaired_det"] or 0.0) > 0.3
        and (r["best_wrong_shape_separable_det"] or 0.0) <= 0.3 and r["has_shape_share"])
    S["best_wrong_given_selected_le_0.3"] = share_le(det, "best_wrong_given")
    pairs = [r for r in rows if r["kind"] == "pair" and r["typical"]]
    S["pair_truth_in_set"] = frac([r["truth"] in r["selected"] + r["ambiguous"] for r in pairs])
    rem = [r for r in rows if r["kind"] == "removed" and r["typical"]]
    S["pair_or_removed_below_oracle"] = len([r for r in rows if r["kind"] in ("pair", "removed") and not r["typical"]])
    S["removed_unexplained_or_partial"] = frac([r["verdict"] in ("unexplained", "partially_explained") for r in rem])
    S["removed_wrong_claimed"] = float(np.mean([r["verdict"] == "explained" for r in rem])) if rem else None
    mags = [abs(r["mag_est"] / r["mag_true"] - 1) for r in det
            if r.get("mag_est") is not None and r.get("mag_true") and r["selected"][:1] == [r["truth"]]]
    S["magnitude_rel_error_median"] = float(np.median(mags)) if mags else None
    per_mag = {}
    for r in det:
        if r.get("mag_est") is not None and r.get("mag_true") and r["selected"][:1] == [r["truth"]]:
            per_mag.setdefault(r["truth"], []).append(abs(r["mag_est"] / r["mag_true"] - 1))
    S["magnitude_rel_error_median_per_effect"] = {k: float(np.median(v)) for k, v in sorted(per_mag.items())}
    secs = [r["seconds"] for r in rows]
    S["seconds_median"], S["seconds_max"] = float(np.median(secs)), float(np.max(secs))
    S["trials"] = len(rows)
    # how many trials each line rests on (typical ones; a share of 3 trials is not one of 30)
    per_effect = {}
    for r in single:
        per_effect[r["truth"]] = per_effect.get(r["truth"], 0) + 1
    S["counts"] = {"none": len(none), "single_typical": len(single), "single_detected": len(det),
                   "shape_separable": len(separable), "pairs": len(pairs), "removed": len(rem),
                   "single_typical_per_effect": dict(sorted(per_effect.items()))}
    return S


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--out", default="bench_blind")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--subset", choices=("ci",), help="the fixed small subset CI runs")
    ap.add_argument("--step", choices=("all", "generate", "run", "score", "shapes", "pool"), default="all",
                    help="shapes: add the shape shares to the labels of a run generated without them; "
                         "pool: score the --runs as one, into OUT/pooled_score.json")
    ap.add_argument("--runs", nargs="+", metavar="DIR", help="with --step pool: the run directories to pool")
    ap.add_argument("--only", help="comma-separated effect names (and/or 'none'): only the plan's trials with them")
    ap.add_argument("--simulator", choices=("ours", "indep"), default="ours",
                    help="draw the trials from mkc_stream.sim (ours) or tools/indep_sim.py (indep)")
    ap.add_argument("--index", help="only these plan positions, e.g. 0,5,20-24 (names keep the position)")
    a = ap.parse_args(argv)
    out = pathlib.Path(a.out)
    if a.step == "pool":
        if not a.runs:
            ap.error("--step pool needs --runs DIR [DIR ...]")
        missing = [d for d in a.runs if not (pathlib.Path(d) / "sealed" / "labels.json").is_file()]
        if missing:
            ap.error(f"not a scored or scorable run (no sealed/labels.json): {', '.join(missing)}")
        try:
            S, _ = step_pool(a.runs, out)
        except ValueError as e:
            ap.error(str(e))
        print(json.dumps(S, indent=1))
        return
    plan = [(k, e, 7919 * (i + 1)) for i, (k, e) in enumerate(CI_SUBSET)] if a.subset else trial_plan(a.trials, a.seed)
    if a.only or a.index:
        plan = select(plan, a.only, a.index)
    if a.step in ("all", "generate"):
        print(f"generating {len(plan)} recordings in {out}/recordings (labels sealed in {out}/sealed)")
        step_generate(out, plan, a.simulator)
    if a.step == "shapes":
        step_shapes(out, plan, a.simulator)
    if a.step in ("all", "run"):
        print("diagnosing (labels unread)")
        step_run(out, a.jobs)
    if a.step in ("all", "score"):
        S, rows = step_score(out)
        for r in rows:
            snr = f"snr {r['oracle_snr']:6.1f}" if r.get("oracle_snr") is not None else " " * 10
            print(f"  {r['trial']} {r['kind']:8s} {str(r['truth']):24s} {snr} -> {r['verdict']:20s} "
                  f"{','.join(r['selected']) or '-':30s} amb {','.join(r['ambiguous']) or '-'}")
        print(json.dumps(S, indent=1))


if __name__ == "__main__":
    main()
