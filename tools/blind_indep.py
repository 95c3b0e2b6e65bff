"""Blind-benchmark trials drawn from the independent simulator (tools/indep_sim.py).

    python tools/blind_benchmark.py --simulator indep --trials 60 --out bench_blind_indep

The trial's effect, magnitude range and forward model are those of tools/blind_benchmark.py
(its ``trial_effects``); this module only hands them the independent simulator's scene in the
shape they read (``traj.t``, ``traj.aux``, ``sensor.noise``; at each stage ``ctx.B``, ``ctx.m``,
``ctx.b``, ``ctx.t``, ``ctx.t_out``, ``ctx.keep``, ``ctx.truth``) and applies each one at its
stage, which tools/indep_sim.py names the same way (field, offset, sensor, noise, range, clock).

What differs from a trial of our simulator, all on the independent simulator's side: its own
attitude process, soft iron (symmetric, det not 1), per-axis white noise (0.03-0.4 uT), clock
(20 Hz nominal here, off by up to 0.5%, whole microseconds), float32 values, and its own aux
processes (a flight or hand-held throttle schedule, current = f(throttle) with its own curve,
a battery's voltage, a board temperature from current heating and ambient moves). The pair
trials keep their confounding: a temperature that only ramps (thermal "ramp") for the
temperature offset and drift, a current that follows throttle alone for the two hard irons.
The current hard iron acts through the true current (before the current sensor's noise);
the diagnoser sees the measured column.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

import indep_sim
from blind_shapes import shape_shares


class _Injector:
    """inject(stage, scene) for indep_sim.simulate: builds the trial's forward models from the
    scene at its first stage, then applies each at its own stage."""

    def __init__(self, bench, kind, truth, rng):
        self.bench, self.kind, self.truth, self.rng = bench, kind, truth, rng
        self.effects, self.magnitude = None, None

    def __call__(self, stage, scene):
        if self.effects is None:
            aux = dict(scene.aux)
            if scene.current_true is not None:
                aux["current"] = scene.current_true        # the field follows the true current
            traj = SimpleNamespace(t=scene.t, aux=aux, acc=scene.acc_true)
            self.effects, self.magnitude = self.bench.trial_effects(self.kind, self.truth, self.rng, traj,
                                                                    SimpleNamespace(noise=scene.noise))
        for eff in self.effects:
            if eff.stage == stage:
                eff.apply(scene, {})


def trial_settings(kind, effect, rng, rate_hz, duration_s):
    """(truth, keyword arguments of indep_sim.simulate) of a trial; the session (flight or
    hand-held, even odds) is drawn from the trial's rng."""
    truth, other_loads, thermal = effect, True, "load"
    if kind == "pair":
        truth = effect.split("|")[0]
        thermal = "ramp" if truth == "temperature_offset" else "load"
        other_loads = truth != "current_hard_iron"
    session = "hand" if rng.uniform() < 0.5 else "flight"
    return truth, {"samples": int(round(duration_s * rate_hz)), "session": session, "other_loads": other_loads,
                   "thermal": thermal, "rate_hz": rate_hz}


def make_indep_trial(kind, effect, seed, bench=None):
    """(Recording, label) of one blind trial from the independent simulator; label as
    tools/blind_benchmark.py's make_trial gives it (kind, truth, pair, magnitude, oracle_snr,
    exclude)."""
    if bench is None:
        import blind_benchmark as bench
    rng = np.random.default_rng(seed)
    truth, kw = trial_settings(kind, effect, rng, bench.RATE, bench.DURATION)
    label = {"kind": kind, "truth": None, "pair": None, "magnitude": None}
    inject = _Injector(bench, kind, truth, rng) if truth is not None else None
    rec, sim_truth = indep_sim.simulate(seed=seed + 1, inject=inject, **kw)
    if truth is not None:
        label.update(truth=truth, magnitude=dict(inject.magnitude),
                     pair=effect.split("|") if kind == "pair" else None)
    if truth is not None:
        _, clean_truth = indep_sim.simulate(seed=seed + 1, **kw)      # the same draws, no effect
        scene, clean = sim_truth["scene"], clean_truth["scene"]
        if truth in bench.ORACLE_EFFECTS:
            label["oracle_snr"] = bench.oracle_snr(
                SimpleNamespace(mag_full=scene.m), SimpleNamespace(mag_full=clean.m, ctx=clean, recording=rec),
                SimpleNamespace(acc=clean.acc_true), SimpleNamespace(noise=clean.noise))
        label["shape_share"] = shape_shares(rec.t, rec.aux, scene.m - clean.m)
    if label["magnitude"] and label["magnitude"].get("from_ctx"):
        label["magnitude"]["value"] = float(sim_truth["injected"][label["magnitude"].pop("from_ctx")])
    label["exclude"] = [truth] if kind == "removed" else []
    return rec, label
