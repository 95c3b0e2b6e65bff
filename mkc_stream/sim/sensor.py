"""The sensor model and the simulator.

m_raw = S^-1 (F u) + b + effects + noise (+ disturbance bursts), with u the true field
direction in the sensor frame from a trajectory, S the soft-iron correction of the recording
spec (m_cal = S (m_raw - b), symmetric, det 1), b the hard iron and F the field strength, all in
uT. Effects are applied stage by stage (``field``: the field the magnetometer senses, before the
iron; ``offset``: added to the raw signal; ``sensor``: gain and shape errors of the sensor;
``noise``; ``range``: clipping and quantization; ``clock``: timestamps and lost samples).
The accelerometer and gyroscope get white noise; aux signals pass through.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.recording import Recording
from .effects import EFFECTS, STAGES, SimContext
from .trajectory import Trajectory


@dataclass
class SensorModel:
    field: float = 50.0                       # uT
    hard_iron: tuple = (12.0, -7.0, 20.0)     # uT
    soft_iron: np.ndarray | None = None       # S (3, 3); None: a mild fixed one
    noise: object = 0.1                       # uT RMS, scalar or per axis
    lsb: float = 0.0                          # uT; 0 = continuous output
    burst_fraction: float = 0.0               # fraction of samples inside disturbance bursts
    burst_length: tuple = (10, 50)            # samples
    burst_magnitude: tuple = (5.0, 40.0)      # uT
    acc_noise: float = 0.03                   # m/s^2
    gyro_noise: float = 0.003                 # rad/s

    def S(self) -> np.ndarray:
        if self.soft_iron is not None:
            return np.asarray(self.soft_iron, dtype=np.float64)
        S = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 0.985]])
        return S / np.linalg.det(S) ** (1.0 / 3.0)


@dataclass
class Simulation:
    recording: Recording              # what a user would record (after drops)
    truth: dict                       # b, S, F, effects, disturbed mask ...
    t_true: np.ndarray                # (N,) true sampling instants, before drops
    mag_full: np.ndarray              # (N, 3) raw magnetometer, before drops
    t_out_full: np.ndarray            # (N,) reported timestamps, before drops
    keep: np.ndarray                  # (N,) samples that survived the drops
    ctx: object = field(repr=False, default=None)


def _resolve(effects):
    """[(effect object, params dict)] from names, (name, params) pairs or custom objects."""
    out = []
    for item in effects or ():
        if isinstance(item, str):
            obj, params = item, {}
        else:
            obj, params = item
        if isinstance(obj, str):
            if obj not in EFFECTS:
                raise ValueError(f"unknown effect {obj!r}; the library has {', '.join(sorted(EFFECTS))}")
            obj = EFFECTS[obj]
        if getattr(obj, "stage", None) not in STAGES:
            raise ValueError(f"effect {obj!r} has no valid stage (one of {STAGES})")
        out.append((obj, dict(params or {})))
    return out


def simulate(traj: Trajectory, sensor: SensorModel | None = None, effects=(), seed=0,
             meta: dict | None = None) -> Simulation:
    """Simulate a recording along ``traj``.

    effects: names, ``(name, {param: value})`` pairs, or objects with ``stage`` and
    ``apply(ctx, params)`` (custom forward models, e.g. the blind benchmark's injections).
    seed: anything ``np.random.default_rng`` takes; a Generator is used as it is, so a preset
    that drew its platform from it continues the same stream (:mod:`.presets`).
    """
    sensor = sensor or SensorModel()
    rng = np.random.default_rng(seed)
    n = len(traj)
    S = sensor.S()
    b = np.asarray(sensor.hard_iron, dtype=np.float64)
    F = float(sensor.field)
    ctx = SimContext(t=traj.t.copy(), B=F * traj.field_dir, m=np.zeros((n, 3)), aux=dict(traj.aux),
                     b=b, S=S, F=F, rng=rng, t_out=traj.t.copy(), keep=np.ones(n, dtype=bool),
                     field_at=lambda tq: F * traj.field_at(tq))
    todo = _resolve(effects)

    def run(stage):
        for eff, params in todo:
            if eff.stage == stage:
                eff.apply(ctx, params)

    run("field")
    ctx.m = ctx.B @ np.linalg.inv(S).T + b
    run("offset")
    disturbed = np.zeros(n, dtype=bool)
    if sensor.burst_fraction > 0:
        from ..calib.synthetic import burst_mask_and_offsets

        disturbed, offs = burst_mask_and_offsets(rng, n, sensor.burst_fraction, sensor.burst_length,
                                                 sensor.burst_magnitude)
        ctx.m += offs
    run("sensor")
    ctx.m += rng.normal(size=(n, 3)) * np.broadcast_to(np.asarray(sensor.noise, dtype=np.float64), (3,))
    run("noise")
    if sensor.lsb > 0:
        ctx.m[:] = np.round(ctx.m / sensor.lsb) * sensor.lsb
    run("range")
    run("clock")

    aux = {}
    if traj.acc is not None:
        acc = traj.acc + rng.normal(0.0, sensor.acc_noise, (n, 3)) if sensor.acc_noise > 0 else traj.acc
        aux.update(ax=acc[:, 0], ay=acc[:, 1], az=acc[:, 2])
    if traj.gyro is not None:
        gyr = traj.gyro + rng.normal(0.0, sensor.gyro_noise, (n, 3)) if sensor.gyro_noise > 0 else traj.gyro
        aux.update(gx=gyr[:, 0], gy=gyr[:, 1], gz=gyr[:, 2])
    aux.update({k: np.asarray(v, dtype=np.float64) for k, v in traj.aux.items()})
    keep = ctx.keep
    rate = 1.0 / np.median(np.diff(traj.t)) if n > 1 else float("nan")
    rec_meta = {"source": "mkc_stream.sim", "units.mag": "uT", "units.acc": "m/s^2", "units.gyr": "rad/s",
                "rate_hz": f"{rate:.6g}", "trajectory": traj.name}
    rec_meta.update(meta or {})
    rec = Recording(t=ctx.t_out[keep], mag=ctx.m[keep], aux={k: v[keep] for k, v in aux.items()}, meta=rec_meta)
    truth = {"hard_iron": b, "soft_iron": S, "field": F, "noise": sensor.noise, "disturbed": disturbed,
             "effects": [(getattr(e, "name", type(e).__name__), p) for e, p in todo], **ctx.truth}
    return Simulation(recording=rec, truth=truth, t_true=ctx.t, mag_full=ctx.m, t_out_full=ctx.t_out,
                      keep=keep, ctx=ctx)
