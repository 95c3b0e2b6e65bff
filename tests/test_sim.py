"""Simulator and effect library: every forward model's units and magnitude, the registry,
trajectories, and the `simulate` command's round trip through the recording format."""
import json

import numpy as np
import pytest

from mkc_stream.io.recording import read_recording
from mkc_stream.sim import EFFECTS, SensorModel, from_recording, generate, parse_effect, simulate
from mkc_stream.sim.effects import SimContext
from mkc_stream.sim.effects.nonlinear import fibonacci_sphere

B0 = np.array([10.0, -5.0, 20.0])


def ctx(n=2000, rate=50.0, aux=None, B=None, seed=0):
    t = np.arange(n) / rate
    if B is None:
        ang = 2 * np.pi * t / 20.0
        B = 50.0 * np.stack([np.cos(ang), np.sin(ang), 0.3 * np.sin(0.5 * ang)], 1)
        B = 50.0 * B / np.linalg.norm(B, axis=1, keepdims=True)
    Bc = B.copy()
    return SimContext(t=t, B=B.copy(), m=B.copy() + B0, aux=dict(aux or {}), b=B0.copy(), S=np.eye(3), F=50.0,
                      rng=np.random.default_rng(seed), t_out=t.copy(), keep=np.ones(n, bool),
                      field_at=lambda tq: np.stack([np.interp(tq, t, Bc[:, j]) for j in range(3)], 1))


def added(name, params, **kw):
    c = ctx(**kw)
    m0, B0c = c.m.copy(), c.B.copy()
    EFFECTS[name].apply(c, params)
    return c, c.m - m0, B0c


def test_registry_names_params_and_units():
    spec = {"temperature_offset", "temperature_scale", "current_hard_iron", "throttle_hard_iron", "hard_iron_drift",
            "hard_iron_step", "bias_random_walk", "scale_nonlinearity", "saturation", "cross_axis",
            "higher_order_soft_iron", "quantization", "colored_noise", "latency", "timestamp_jitter", "sample_drops",
            "hysteresis", "misalignment"}
    assert spec <= set(EFFECTS)
    for e in EFFECTS.values():
        assert e.kind in ("mean", "noise", "clock", "mask") and e.params and e.doc
        for p in e.params:
            assert p.unit and p.low <= p.high


def test_parse_effect_and_errors():
    assert parse_effect("current_hard_iron:kx=0.2,ky=0") == ("current_hard_iron", {"kx": 0.2, "ky": 0.0})
    assert parse_effect("latency") == ("latency", {})
    with pytest.raises(ValueError, match="unknown effect"):
        parse_effect("magic")
    with pytest.raises(ValueError, match="no parameter"):
        parse_effect("latency:delay=3,foo=1")
    with pytest.raises(ValueError, match="not a number"):
        parse_effect("latency:delay=abc")


def test_thermal_offset_and_scale_units():
    T = np.full(2000, 35.0)
    _, d, _ = added("temperature_offset", {"cx": 10, "cy": 0, "cz": -20, "tau": 0, "t_ref": 25}, aux={"temp": T})
    assert np.allclose(d, [0.1, 0.0, -0.2])                     # 10 nT/degC x 10 degC = 0.1 uT
    step = np.where(np.arange(2000) / 50.0 >= 10.0, 35.0, 25.0)
    _, d, _ = added("temperature_offset", {"cx": 10, "cy": 0, "cz": 0, "tau": 5.0, "t_ref": 25}, aux={"temp": step})
    k = int((10.0 + 5.0) * 50)
    assert d[k, 0] == pytest.approx(0.1 * (1 - np.exp(-1)), rel=0.02)   # thermal lag: 63% after tau
    c, d, _ = added("temperature_scale", {"ax": 0.1, "ay": 0, "az": 0, "tau": 0, "t_ref": 25}, aux={"temp": T})
    assert np.allclose(d[:, 0], 0.01 * (c.m[:, 0] - d[:, 0] - B0[0]))  # 0.1 %/degC x 10 degC = 1% gain


def test_electrical_and_drift_units():
    n = 2000
    _, d, _ = added("current_hard_iron", {"kx": 0.1, "ky": -0.2, "kz": 0}, aux={"current": np.full(n, 5.0)})
    assert np.allclose(d, [0.5, -1.0, 0.0])
    _, d, _ = added("throttle_hard_iron", {"kx": 2, "ky": 0, "kz": 0, "exponent": 1.5},
                    aux={"throttle": np.full(n, 0.25)})
    assert np.allclose(d[:, 0], 2 * 0.25 ** 1.5)
    c, d, _ = added("hard_iron_drift", {"vx": 1.0, "vy": 0, "vz": 0}, n=3601, rate=1.0)
    assert d[-1, 0] == pytest.approx(1.0)                      # 1 uT/h over an hour
    c, d, _ = added("hard_iron_step", {"dx": 0.5, "dy": 0, "dz": 0, "t_step": 10.0})
    assert np.all(d[c.t < 10, 0] == 0) and np.allclose(d[c.t >= 10, 0], 0.5)
    with pytest.raises(ValueError, match="needs the aux signal 'current'"):
        added("current_hard_iron", {})


def test_random_walk_intensity():
    c, d, _ = added("bias_random_walk", {"q": 60.0}, n=20000, rate=10.0, seed=3)   # 60 uT/sqrt(h) = 1 uT/sqrt(s)
    inc = np.diff(d[::10], axis=0)                              # 1 s increments
    assert np.std(inc) == pytest.approx(1.0, rel=0.05)


def test_nonlinear_family_magnitudes():
    B = np.zeros((3, 3))
    B[0, 0] = 50.0
    _, d, _ = added("scale_nonlinearity", {"bx": 100, "by": 0, "bz": 0}, B=B, n=3)
    assert d[0, 0] == pytest.approx(0.1)                       # 100 nT at 50 uT
    c, d, _ = added("saturation", {"limit": 40.0})
    assert c.m.max() <= 40.0 and c.m.min() >= -40.0 and np.any(c.m == 40.0)
    u = fibonacci_sphere(3000) * 50.0
    _, d, _ = added("higher_order_soft_iron", {"q": 0.3, "pattern": 2}, B=u, n=3000)
    assert np.sqrt(np.mean(np.sum(d * d, axis=1))) == pytest.approx(0.3, rel=0.02)   # RMS over directions at 50 uT
    t = np.arange(2000) / 50.0
    B = np.stack([50 * np.sin(2 * np.pi * t / 4), np.zeros_like(t), np.zeros_like(t)], 1)
    _, d, _ = added("hysteresis", {"width": 0.2}, B=B)
    rising = (np.gradient(B[:, 0]) > 0.5) & (t > 0.1)          # the loop starts closed at the first sample
    falling = np.gradient(B[:, 0]) < -0.5
    assert np.allclose(d[rising, 0], -0.2, atol=1e-9) and np.allclose(d[falling, 0], 0.2, atol=1e-9)
    turning = np.flatnonzero(np.diff(np.sign(np.diff(B[:, 0]))) < 0)[0] + 1     # the first maximum
    assert np.allclose(d[turning:turning + 4, 0], -0.2 - (B[turning:turning + 4, 0] - B[turning, 0]))
    # rate-independent: the same field values traversed twice as slowly give the same loop
    _, d_slow, _ = added("hysteresis", {"width": 0.2}, B=B, rate=25.0)
    assert np.array_equal(d_slow, d)


def test_alignment_effects_rotate_the_sensed_field():
    c, _, B = added("misalignment", {"roll": 1.0, "pitch": 0.0, "yaw": 0.0})
    cos = np.sum(c.B * B, 1) / (np.linalg.norm(c.B, axis=1) * np.linalg.norm(B, axis=1))
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert ang.max() == pytest.approx(1.0, abs=0.01)
    assert np.allclose(np.linalg.norm(c.B, axis=1), 50.0)      # a rotation keeps the field strength
    c, _, B = added("cross_axis", {"xy": 1.0, "xz": 0, "yx": 0, "yz": 0, "zx": 0, "zy": 0})
    assert np.allclose(c.B[:, 0] - B[:, 0], np.radians(1.0) * B[:, 1])


def test_noise_effects():
    c, d, _ = added("quantization", {"lsb": 0.25, "offset": 0.0})
    assert np.allclose(c.m / 0.25, np.round(c.m / 0.25))
    c, d, _ = added("colored_noise", {"sigma": 0.2, "tau": 2.0}, n=50000, rate=10.0, seed=1)
    assert np.std(d) == pytest.approx(0.2, rel=0.08)
    r1 = np.corrcoef(d[1:, 0], d[:-1, 0])[0, 1]
    assert r1 == pytest.approx(np.exp(-0.1 / 2.0), abs=0.01)


def test_timing_effects():
    c, _, B = added("latency", {"delay": 40.0})
    assert np.allclose(c.B[10:], c.field_at(c.t[10:] - 0.04))
    c = ctx(n=20000)
    EFFECTS["timestamp_jitter"].apply(c, {"sigma": 1.0})
    assert np.std(c.t_out - c.t) * 1e3 == pytest.approx(1.0, rel=0.05) and np.all(np.diff(c.t_out) >= 0)
    c = ctx(n=20000)
    EFFECTS["sample_drops"].apply(c, {"fraction": 0.03, "run": 2.0})
    assert (~c.keep).mean() == pytest.approx(0.03, abs=0.002)


def test_latency_output_filter_lowers_the_field_strength_at_fast_turns():
    """A delay alone turns the field and keeps its strength; an output filter of RMS width s
    also averages directions a turn spreads apart: |B| drops by s^2 |dB/dt|^2 / (2 |B|)."""
    w = 2 * np.pi / 1.5                                        # rad/s: a fast turn about z
    t = np.arange(3000) / 100.0

    def field(tq):
        return 50.0 * np.stack([np.cos(w * tq), np.sin(w * tq), np.zeros_like(tq)], 1)

    def run(params):
        c = SimContext(t=t, B=field(t), m=field(t) + B0, aux={}, b=B0.copy(), S=np.eye(3), F=50.0,
                       rng=np.random.default_rng(0), t_out=t.copy(), keep=np.ones(t.size, bool), field_at=field)
        EFFECTS["latency"].apply(c, params)
        return c.B

    B = run({"delay": 20.0})
    assert np.allclose(B, field(t - 0.02)) and np.allclose(np.linalg.norm(B, axis=1), 50.0)
    s = 0.03
    B = run({"delay": 20.0, "spread": s * 1e3})
    drop = 50.0 - np.linalg.norm(B, axis=1)
    assert drop == pytest.approx(np.full(t.size, s ** 2 * (50.0 * w) ** 2 / (2 * 50.0)), rel=0.02)
    # the mean delay is still 20 ms: the filtered field points where the field was 20 ms earlier
    ang = np.arctan2(B[:, 1], B[:, 0]) - np.arctan2(*field(t - 0.02)[:, [1, 0]].T)
    assert np.abs(np.angle(np.exp(1j * ang))).max() < 1e-6


def test_trajectories():
    from mkc_stream.calib.quality import sphere_coverage

    for motion in ("hand", "figure8", "flight"):
        tr = generate(motion, duration=60, rate=20, seed=1, power=True)
        assert np.allclose(np.linalg.norm(tr.field_dir, axis=1), 1.0)
        assert np.allclose(np.linalg.norm(tr.acc, axis=1), 9.81, atol=2.0)
        assert set(tr.aux) == {"temp", "throttle", "current", "voltage"}
        assert np.all((tr.aux["throttle"] >= 0) & (tr.aux["throttle"] <= 1))
    assert sphere_coverage(generate("hand", duration=200, rate=20, seed=2).field_dir) > 0.9
    ramp = generate("hand", duration=100, rate=10, seed=2, temp="ramp").aux["temp"]
    assert ramp[-1] - ramp[0] > 5


def test_simulate_truth_and_recording_driven_trajectory():
    tr = generate("hand", duration=100, rate=20, seed=4)
    sim = simulate(tr, SensorModel(noise=0.05), seed=5)
    mc = (sim.recording.mag - sim.truth["hard_iron"]) @ sim.truth["soft_iron"].T
    assert np.abs(np.linalg.norm(mc, axis=1) - 50.0).max() < 0.5
    back = from_recording(sim.recording)
    ang = np.degrees(np.arccos(np.clip(np.sum(back.field_dir * tr.field_dir, 1), -1, 1)))
    # directions implied by the data, turned onto the accelerometer's cone of constant dip: as
    # exact as the accelerometer (its linear accelerations tilt it by ~1-2 deg)
    assert np.median(ang) < 2.0
    assert len(back) == len(tr) and set(back.aux) == {"temp"}
    mag_only = sim.recording
    mag_only.aux = {"temp": mag_only.aux["temp"]}
    back = from_recording(mag_only)
    ang = np.degrees(np.arccos(np.clip(np.sum(back.field_dir * tr.field_dir, 1), -1, 1)))
    assert np.median(ang) < 0.6


def test_simulate_command_round_trip(tmp_path, capsys):
    from mkc_stream.cli import main

    out = tmp_path / "sim.csv"
    code = main(["simulate", "--trajectory", "hand", "--duration", "30", "--rate", "20", "--power", "--seed", "3",
                 "--effect", "current_hard_iron:kx=0.2", "--effect", "hard_iron_step:dx=1", "--out", str(out)])
    assert code == 0
    rec = read_recording(out)
    assert len(rec) == 600 and not rec.bad_rows
    assert rec.columns == ["t", "mx", "my", "mz", "ax", "ay", "az", "gx", "gy", "gz",
                           "temp", "throttle", "current", "voltage"]
    again = tmp_path / "again.csv"
    rec.write(again)
    rec2 = read_recording(again)
    assert np.array_equal(rec.mag, rec2.mag) and np.array_equal(rec.t, rec2.t)
    assert main(["simulate", "--effect", "nope", "--out", str(out)]) == 2
    assert main(["simulate", "--effect", "latency"]) == 2            # no --out
    assert main(["simulate", "--list-effects"]) == 0
    assert "temperature_offset" in capsys.readouterr().out
    json.dumps(EFFECTS["latency"].defaults())
