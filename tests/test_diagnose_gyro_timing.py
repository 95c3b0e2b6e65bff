"""The magnetometer's timing against the gyroscope (diagnose.gyro_timing) and its part in the
latency test: it reads a few milliseconds that the accelerometer's noise hides, whatever the
gyroscope's unit and axes, says "not testable" when the sensor does not turn, and keeps the
latency test's level (Bonferroni over its two views)."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from mkc_stream.diagnose import diagnose
from mkc_stream.diagnose.baseline import fit_baseline
from mkc_stream.diagnose.frame import prepare
from mkc_stream.diagnose.gyro_timing import gyro_delay
from mkc_stream.diagnose.matched import T_CAP, MatchedTests
from mkc_stream.diagnose.report import text
from mkc_stream.sim import SensorModel, generate, simulate

GYRO = ("gx", "gy", "gz")


@pytest.fixture(scope="module")
def trajectory():
    return generate("hand", duration=300, rate=20, seed=11, power=True)


def _rec(trajectory, delay):
    eff = [("latency", {"delay": delay})] if delay else []
    return simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=12).recording


def _timing(rec):
    frame = prepare(rec, 20000)
    base = fit_baseline(frame)
    return gyro_delay(frame, base.fit.state, base.valid[:, 0])


def test_gyro_timing_reads_a_5_ms_latency_and_nothing_without_one(trajectory):
    late = _timing(_rec(trajectory, 5.0))
    assert late["testable"] and abs(late["delay_ms"] - 5.0) < 0.3 and late["t"] > 20    # 5.01 ms, t 48
    none = _timing(_rec(trajectory, 0.0))
    assert none["testable"] and abs(none["delay_ms"]) < 0.3 and abs(none["t"]) < 3       # -0.004 ms, t -0.04
    assert none["p"] > 0.01


def test_gyro_timing_does_not_depend_on_the_gyroscopes_unit_or_axes(trajectory):
    """The gyroscope's map to the magnetometer's frame is fitted first, so deg/s, swapped axes
    and a flipped sign give the same delay in seconds."""
    rec = _rec(trajectory, 5.0)
    aux = dict(rec.aux)
    g = np.stack([aux.pop(c) for c in GYRO], axis=1)
    g = np.degrees(g)[:, [2, 0, 1]] * np.array([-1.0, 1.0, 1.0])
    aux.update(zip(GYRO, g.T))
    a, b = _timing(rec), _timing(dataclasses.replace(rec, aux=aux))
    assert b["testable"] and b["delay_ms"] == pytest.approx(a["delay_ms"], rel=1e-6)
    assert b["t"] == pytest.approx(a["t"], rel=1e-6)


def test_gyro_timing_is_not_testable_without_rotation_or_gyroscope():
    rng = np.random.default_rng(3)
    n = 4000
    frame = SimpleNamespace(t=np.arange(n) / 20.0, m=np.array([20.0, 5.0, -40.0]) + rng.normal(0, 0.1, (n, 3)),
                            gyro=rng.normal(0, 0.003, (n, 3)), block=np.arange(n) * 32 // n, n_blocks=32, n=n)
    state = SimpleNamespace(b=np.zeros(3), S=np.eye(3))
    r = gyro_delay(frame, state)
    assert r["testable"] is False and r["reason"]
    assert gyro_delay(SimpleNamespace(gyro=None), state) == {"testable": False, "reason": "no gyroscope columns"}


def test_latency_test_takes_the_smaller_p_value_doubled():
    mt = MatchedTests.__new__(MatchedTests)
    out = {"Q": 1.0, "t": 2.5, "p": float(stats.t.sf(2.5, 39)), "design": 0}
    mt.gyro = {"t": 0.0, "dof": 31}                   # a gyroscope that sees nothing
    r = mt._with_gyro(out, 40)
    assert r["p"] == pytest.approx(2 * out["p"]) and r["t"] < out["t"] and r["t_channels"] == 2.5
    mt.gyro = {"t": -60.0, "dof": 31}                 # a magnetometer far early: two-sided
    r = mt._with_gyro(out, 40)
    assert r["p"] < 1e-20 and 30 < r["t"] <= T_CAP


def test_a_latency_only_the_gyroscope_sees_is_named(trajectory):
    """5 ms: the dip channel's test gives t 2.8 (below its Bonferroni alarm) and the gap index
    stays at its null level; the gyroscope's test gives t 48."""
    rec = _rec(trajectory, 5.0)
    d = diagnose(rec, replicas=24)
    assert d.verdict == "explained" and d.selected == ["latency"]
    assert d.info["detected_by"] == "matched tests"
    lat = {e.name: e for e in d.effects}["latency"]
    assert abs(lat.magnitude["gyro_delay_ms"] - 5.0) < 0.3
    assert abs(d.info["gyro_timing"]["delay_ms"] - 5.0) < 0.3
    assert "gyro timing   : magnetometer late by 5.0" in text(d)
    blind = dataclasses.replace(rec, aux={k: v for k, v in rec.aux.items() if k not in GYRO})
    d = diagnose(blind, replicas=24)
    assert d.verdict == "no_gap" and d.info["gyro_timing"] is None
