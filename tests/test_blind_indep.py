"""The independent simulator with effects (tools/indep_sim.py: simulate, its aux sessions and
injection stages) and the blind benchmark's trials drawn from it (tools/blind_indep.py,
``tools/blind_benchmark.py --simulator indep``)."""
import json
import pathlib
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

import blind_benchmark  # noqa: E402
import blind_indep  # noqa: E402
import indep_sim  # noqa: E402

#: values of simulate_null computed by the null-only simulator before effects were added to it
#: (elementwise paths only: times, the quaternion integration, the drawn noise and field, the
#: accelerometer and the temperature; the magnetometer goes through a matrix product)
NULL_VALUES = [
    ((400, 4), {}, {
        "t": (3514.714903, 3518.704504), "temp": (31.59, 31.59), "ax7": 2.0557167530059814,
        "az_last": 2.9097979068756104,
        "q_last": (-0.46955924486776224, 0.03405569032670565, 0.8092740194723307, 0.3513258984514044),
        "noise": (0.44170928244526214, 0.3005608600951382, 0.39721374606714743),
        "field": (-19.156213312138984, 18.801658068352907, 8.755817130717954),
        "w_last": (0.8885061184671538, 0.7125935012596106, -0.6195595077048719)}),
    ((300, 9), {"rate_hz": 50.0, "noise_scale": 0.5}, {
        "t": (1039.67378, 1045.631654), "temp": (28.84, 28.87), "ax7": 8.620301246643066,
        "az_last": 0.3476664423942566,
        "q_last": (0.24501778130333368, 0.6796968819813334, 0.2103621570880953, -0.6585789233913341),
        "noise": (0.08329559801119743, 0.09288168854676933, 0.09281149496082577),
        "field": (-7.632400952746215, -35.262118653820615, 33.34195629084341),
        "w_last": (0.015041111805904912, -0.682719718055958, -0.15605033220123568)}),
]


@pytest.mark.parametrize("args,kw,want", NULL_VALUES)
def test_simulate_null_keeps_its_values(args, kw, want):
    rec, truth = indep_sim.simulate_null(*args, **kw)
    got = {"t": (rec.t[0], rec.t[-1]), "temp": (rec.aux["temp"][0], rec.aux["temp"][-1]), "ax7": rec.aux["ax"][7],
           "az_last": rec.aux["az"][-1], "q_last": truth["quaternion"][-1], "noise": truth["noise_uT"],
           "field": truth["field_ned_uT"], "w_last": truth["body_rate_rad_s"][-1]}
    for key, value in want.items():
        np.testing.assert_allclose(np.asarray(got[key], dtype=float), value, rtol=1e-12, atol=1e-12, err_msg=key)
    assert rec.meta["null"] == "no effect of the library"
    assert "scene" not in truth and set(rec.aux) == {"ax", "ay", "az", "gx", "gy", "gz", "temp"}


def test_a_session_adds_aux_after_the_null_draws():
    """The sensor, attitude and noise of a session's recording are those of the null of the same seed."""
    null, _ = indep_sim.simulate_null(1500, seed=3, rate_hz=20.0)
    rec, truth = indep_sim.simulate(1500, seed=3, rate_hz=20.0, session="flight")
    assert np.array_equal(rec.mag, null.mag) and np.array_equal(rec.t, null.t)
    assert {"throttle", "current", "voltage", "temp"} <= set(rec.aux) and "null" not in rec.meta
    thr, cur = rec.aux["throttle"], rec.aux["current"]
    assert 0.0 <= thr.min() and thr.max() <= 1.0 and thr.max() > 0.2
    assert np.corrcoef(thr, cur)[0, 1] > 0.5                        # current = f(throttle) + other loads
    assert not np.array_equal(rec.aux["temp"], null.aux["temp"])    # the board's thermal model


def test_bad_session_arguments_are_refused():
    with pytest.raises(ValueError, match="session"):
        indep_sim.simulate(100, session="boat")
    with pytest.raises(ValueError, match="thermal"):
        indep_sim.simulate(100, session="hand", thermal="sauna")


def _pair(inject, n=2000, seed=21, **kw):
    """(recording with the injection, recording without it) of the same draws."""
    kw = {"rate_hz": 20.0, "session": "hand", **kw}
    return indep_sim.simulate(n, seed, inject=inject, **kw), indep_sim.simulate(n, seed, **kw)


def test_an_offset_stage_current_hard_iron_adds_k_times_current():
    k = np.array([0.3, -0.2, 0.1])                                   # uT/A

    def inject(stage, scene):
        if stage == "offset":
            scene.m += np.outer(scene.current_true, k)
    (rec, truth), (clean, _) = _pair(inject)
    d = rec.mag - clean.mag
    want = np.outer(truth["scene"].current_true, k)
    assert np.max(np.abs(d - want)) < 1e-4                          # float32 rounding of ~100 uT values
    assert np.ptp(want[:, 0]) > 1.0                                  # the current did vary


def test_a_field_stage_rotation_acts_before_the_soft_and_hard_iron():
    c, s = np.cos(0.03), np.sin(0.03)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def inject(stage, scene):
        if stage == "field":
            assert scene.m is None                                   # nothing read yet
            scene.B[:] = scene.B @ R.T
    (rec, truth), (clean, clean_truth) = _pair(inject)
    B0, A = clean_truth["scene"].B, clean_truth["soft_iron_map"]
    want = (B0 @ R.T - B0) @ A.T
    assert np.max(np.abs(rec.mag - clean.mag - want)) < 1e-4


def test_the_noise_stage_comes_after_the_white_noise_and_the_clock_stage_drops_rows():
    seen = {}

    def inject(stage, scene):
        if stage == "sensor":
            seen["before"] = scene.m.copy()
        elif stage == "noise":
            seen["after"] = scene.m.copy()
        elif stage == "clock":
            scene.keep[::10] = False
    (rec, truth), _ = _pair(inject, n=4000)
    noise = seen["after"] - seen["before"]
    np.testing.assert_allclose(noise.std(axis=0), truth["noise_uT"], rtol=0.06)   # 4000 draws: ~1.1% SE
    assert len(rec) == 3600 and all(len(v) == 3600 for v in rec.aux.values())


def test_a_blind_trial_injects_the_benchmarks_current_hard_iron_through_the_true_current():
    """The adapter hands the benchmark's Biot-Savart wire pair the true current; the change of the
    reading is K current with |K| the label's magnitude."""
    seed = 4242
    rec, label = blind_indep.make_indep_trial("single", "current_hard_iron", seed, blind_benchmark)
    truth, kw = blind_indep.trial_settings("single", "current_hard_iron", np.random.default_rng(seed),
                                           blind_benchmark.RATE, blind_benchmark.DURATION)
    clean, clean_truth = indep_sim.simulate(seed=seed + 1, **kw)
    cur = clean_truth["scene"].current_true
    d = rec.mag - clean.mag
    k = np.array([np.sum(cur * d[:, j]) / np.sum(cur * cur) for j in range(3)])
    assert np.linalg.norm(k) == pytest.approx(label["magnitude"]["value"], rel=1e-3)
    assert np.max(np.abs(d - np.outer(cur, k))) < 1e-4
    assert label["truth"] == "current_hard_iron" and label["oracle_snr"] > 0 and label["exclude"] == []


def test_blind_end_to_end_on_the_independent_simulator(tmp_path):
    """Plan positions 0 (no effect) and 11 (current hard iron) of a 60-trial plan: both are
    generated; the no-effect one is diagnosed and scored (no gap)."""
    blind_benchmark.main(["--simulator", "indep", "--trials", "60", "--index", "0,11", "--out", str(tmp_path),
                          "--step", "generate"])
    labels = json.loads((tmp_path / "sealed" / "labels.json").read_text())
    assert sorted(labels) == ["trial0000", "trial0011"]
    assert labels["trial0011"]["truth"] == "current_hard_iron"
    assert "indep_sim" in (tmp_path / "recordings" / "trial0011.csv").read_text()[:200]
    out = tmp_path / "none"
    blind_benchmark.main(["--simulator", "indep", "--trials", "60", "--index", "0", "--out", str(out)])
    score = json.loads((out / "score.json").read_text())
    S = score["summary"]
    for key in ("false_alarm_rate", "named_first", "named_first_per_effect", "shrink_correct_ge_0.7",
                "pair_truth_in_set", "removed_unexplained_or_partial", "magnitude_rel_error_median", "trials"):
        assert key in S
    assert S["trials"] == 1 and S["false_alarm_rate"] == 0.0
    assert score["rows"][0]["verdict"] == "no_gap"


@pytest.mark.slow  # ~25 s; CI keeps the latency form with test_diagnose.py's filtering-latency test
def test_a_latency_trial_whose_form_closes_the_gap_is_named():
    """The independent simulator's trial 43 of seed 2: an 11.3 ms first-order output lag at 20 Hz.
    Its form measures it (11.3 ms) and closes the held-out gap below the alarm; the trial ended
    `unexplained` while the gap index read the E-step's log sigma, which stops anywhere on its
    flat ridge: the screen's 16 replicas put it at 1.5-2.3 and the recording at 5.2, and the
    latency looked harmful (decision 0028)."""
    from mkc_stream.diagnose import diagnose

    rec, label = blind_indep.make_indep_trial("single", "latency", 200049, blind_benchmark)
    assert label["magnitude"]["value"] == pytest.approx(11.33, abs=0.01)
    d = diagnose(rec, profile="fast", seed=0)
    assert d.selected[:1] == ["latency"] and d.verdict == "explained", (d.verdict, d.selected)
    assert d.gap_after <= d.threshold
    lat = next(e for e in d.effects if e.name == "latency")
    assert lat.magnitude["value"] == pytest.approx(label["magnitude"]["value"], rel=0.1)
