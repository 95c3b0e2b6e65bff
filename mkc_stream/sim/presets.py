"""Ready-made simulations: a trajectory, a platform and a sensor chosen together.

``sweep``: the synthetic calibration stream of :func:`mkc_stream.calib.synthetic.synthetic_mag`
made by the simulator. A hand-held sphere sweep (no accelerometer, gyroscope or aux columns), a
random platform (hard iron uniform in +-hard_iron_scale uT per axis, soft iron S symmetric,
det 1, eigenvalues within about exp(+-soft_spread)), disturbance bursts, white noise and
optional isolated spikes: m_raw = S^-1 (F u) + b + bursts + noise (+ spikes), in uT. For the
same arguments its magnetometer samples, truth and directions are those of ``synthetic_mag``
(the same generator draws in the same order: the platform and the path first, then the
simulator's bursts and noise; spikes from their own generator); ``effects`` adds library
effects on top.
"""
from __future__ import annotations

import numpy as np

from ..calib.synthetic import random_platform, spike_offsets, sphere_sweep
from .effects.form import ReplicaEffect
from .sensor import SensorModel, Simulation, simulate
from .trajectory import Trajectory


def sweep(seed=0, N=2000, field=50.0, noise=0.3, burst_fraction=0.1, burst_length=(20, 60),
          burst_magnitude=(5.0, 40.0), hard_iron_scale=30.0, soft_spread=0.25, rate_hz=50.0,
          spike_fraction=0.0, spike_magnitude=1000.0, effects=()) -> Simulation:
    """The synthetic sweep through the simulator (arguments as :func:`~mkc_stream.calib.synthetic.synthetic_mag`;
    ``effects`` as :func:`~.sensor.simulate`). ``truth`` adds ``directions`` (N, 3), the true unit
    field directions, and its ``disturbed`` marks spikes as well as bursts."""
    rng = np.random.default_rng(seed)
    b, S = random_platform(rng, hard_iron_scale, soft_spread)
    traj = Trajectory(t=np.arange(N) / rate_hz, field_dir=sphere_sweep(rng, N), name="sweep")
    sensor = SensorModel(field=field, hard_iron=b, soft_iron=S, noise=noise, burst_fraction=burst_fraction,
                         burst_length=burst_length, burst_magnitude=burst_magnitude)
    spikes = np.zeros(N, dtype=bool)

    def add_spikes(ctx):
        hit, offs = spike_offsets(seed, N, spike_fraction, spike_magnitude)
        ctx.m[hit] += offs
        spikes[:] = hit

    # spikes first in the noise stage: straight after the white noise, before any noise effect
    todo = ([(ReplicaEffect("spikes", "noise", add_spikes), {})] if spike_fraction > 0 else []) + list(effects)
    # the simulator continues the same generator (default_rng returns a Generator unchanged)
    sim = simulate(traj, sensor, effects=todo, seed=rng, meta={"preset": "sweep"})
    sim.truth["disturbed"] = sim.truth["disturbed"] | spikes
    sim.truth["directions"] = traj.field_dir
    return sim
