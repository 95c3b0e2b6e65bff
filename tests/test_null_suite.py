"""The independent null simulator (tools/indep_sim.py) and the null suite (tools/null_suite.py).

The simulator must make valid recordings with the stated noise, clock and value rounding, and
must not borrow from mkc_stream.sim; the suite must count false alarms as documented."""
import ast
import json
import pathlib
import sys

import numpy as np
import pytest

TOOLS = pathlib.Path(__file__).resolve().parents[1] / "tools"
sys.path.insert(0, str(TOOLS))

import indep_sim  # noqa: E402
import null_suite  # noqa: E402

from mkc_stream.io.recording import read_recording  # noqa: E402


def test_indep_sim_imports_nothing_of_our_simulator():
    tree = ast.parse((TOOLS / "indep_sim.py").read_text())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            mods.add(node.module or "")
    ours = {m for m in mods if m.startswith("mkc_stream")}
    assert ours == {"mkc_stream.io.recording"}, ours       # the recording type and writer only
    assert not any(m.startswith(("mkc_stream.sim", "mkc_stream.calib")) for m in mods)


@pytest.fixture(scope="module")
def null_rec():
    return indep_sim.simulate_null(6000, seed=5)


def test_written_recording_reads_back_whole(null_rec, tmp_path):
    rec, truth = null_rec
    back = read_recording(rec.write(tmp_path / "null.csv"))
    assert back.bad_rows == []
    assert back.columns[:4] == ["t", "mx", "my", "mz"]
    assert set(back.aux) == {"ax", "ay", "az", "gx", "gy", "gz", "temp"}
    assert back.meta["units.mag"] == "uT" and back.meta["units.gyr"] == "rad/s"
    np.testing.assert_array_equal(back.mag, rec.mag)
    np.testing.assert_array_equal(back.t, rec.t)


def test_clock_is_regular_on_whole_microseconds(null_rec):
    rec, truth = null_rec
    us = rec.t * 1e6
    np.testing.assert_allclose(us, np.round(us), atol=1e-3)
    dt = np.diff(rec.t)
    np.testing.assert_allclose(dt, truth["period_s"], atol=1e-9)        # no jitter, no drops
    assert abs(1.0 / truth["period_s"] / truth["odr_hz"] - 1.0) <= 0.0051


def test_values_are_float32_and_noise_is_as_drawn(null_rec):
    rec, truth = null_rec
    for x in (rec.mag, rec.aux["ax"], rec.aux["gz"]):
        np.testing.assert_array_equal(x.astype(np.float32).astype(np.float64), x)
    # white noise per axis from third differences (variance 20 sigma^2; the motion's third
    # difference is ~(w dt)^3 F, below 1e-3 uT here)
    m = rec.mag
    d3 = m[3:] - 3 * m[2:-1] + 3 * m[1:-2] - m[:-3]
    est = d3.std(axis=0) / np.sqrt(20.0)
    np.testing.assert_allclose(est, truth["noise_uT"], rtol=0.06)
    # the field strength after the drawn platform is removed is the drawn field
    Ainv = np.linalg.inv(truth["soft_iron_map"])
    F = np.linalg.norm((m - truth["hard_iron_uT"]) @ Ainv.T, axis=1)
    assert abs(np.median(F) - truth["field_uT"]) < 0.05
    A = truth["soft_iron_map"]
    np.testing.assert_allclose(A, A.T)
    assert np.all(np.linalg.eigvalsh(A) > 0)


def test_gyroscope_and_attitude_refer_to_the_same_instant(null_rec):
    rec, truth = null_rec
    q, w, dt = truth["quaternion"], truth["body_rate_rad_s"], truth["period_s"]
    B = indep_sim.world_to_body(q, truth["field_ned_uT"])
    # a constant world field seen from a turning body: dB/dt = -w x B; a gyroscope late by
    # delta leaves r = delta (dw/dt x B): the fitted delta must be ~0 (well below a microsecond)
    r = (B[2:] - B[:-2]) / (2 * dt) + np.cross(w[1:-1], B[1:-1])
    X = np.cross((w[2:] - w[:-2]) / (2 * dt), B[1:-1])
    delta = float(np.sum(X * r) / np.sum(X * X))
    assert abs(delta) < 1e-5
    acc = np.stack([rec.aux[c] for c in ("ax", "ay", "az")], axis=1)
    assert abs(np.median(np.linalg.norm(acc, axis=1)) - indep_sim.GRAVITY) < 0.1
    # the field-to-specific-force angle is 90 deg plus the inclination (specific force points up)
    u = B / np.linalg.norm(B, axis=1, keepdims=True)
    g = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    inc = np.degrees(np.arcsin(truth["field_ned_uT"][2] / truth["field_uT"]))
    assert abs(np.median(np.degrees(np.arccos(np.sum(u * g, axis=1)))) - (90.0 + inc)) < 0.5


def test_a_seed_draws_the_same_platform_at_every_length():
    _, short = indep_sim.simulate_null(1000, seed=7)
    _, long = indep_sim.simulate_null(3000, seed=7)
    for key in ("noise_uT", "hard_iron_uT", "soft_iron_map", "field_ned_uT", "gyro_gain"):
        np.testing.assert_array_equal(short[key], long[key])
    _, quiet = indep_sim.simulate_null(1000, seed=7, noise_scale=0.25)
    np.testing.assert_allclose(quiet["noise_uT"], 0.25 * short["noise_uT"])
    _, iso = indep_sim.simulate_null(1000, seed=7, isotropic_noise=True)
    np.testing.assert_allclose(iso["noise_uT"], np.sqrt(np.mean(short["noise_uT"] ** 2)))
    np.testing.assert_array_equal(iso["hard_iron_uT"], short["hard_iron_uT"])


def test_lsb_rounds_and_bad_arguments_are_refused():
    rec, _ = indep_sim.simulate_null(500, seed=1, lsb=0.25)
    k = rec.mag / 0.25
    assert np.max(np.abs(k - np.round(k))) < 1e-4          # multiples of the LSB (then float32)
    with pytest.raises(ValueError, match="lsb"):
        indep_sim.simulate_null(500, lsb=-1.0)
    with pytest.raises(ValueError, match="noise_scale"):
        indep_sim.simulate_null(500, noise_scale=float("nan"))
    with pytest.raises(ValueError, match="samples"):
        indep_sim.simulate_null(5)


def _row(family, verdict, on_testable=None, selected=(), seconds=1.0):
    return {"family": family, "index": 0, "name": "x", "samples": 1000, "seconds": seconds, "verdict": verdict,
            "verdict_on_testable": on_testable or verdict, "baseline_accepted": verdict != "baseline_rejected",
            "false_alarm": (on_testable or verdict) != "no_gap", "gap_before": 1.0, "gap_after": 1.0, "alarm": 1.2,
            "detected_by": None if verdict == "no_gap" else "gap index", "matched_fired": [],
            "selected": list(selected), "ambiguous_with": [], "where": [], "decimation": 1,
            "rejected_for": "coverage" if verdict == "baseline_rejected" else None}


def test_summary_counts_false_alarms_and_rejections():
    rows = [_row("a", "no_gap", seconds=2.0), _row("a", "explained", selected=["latency"], seconds=4.0),
            _row("a", "baseline_rejected", on_testable="no_gap", seconds=9.0),
            {"family": "b", "index": 0, "name": "short", "error": "not diagnosed: too short"}]
    s = null_suite.summarise(rows)
    assert s["a"]["recordings"] == 3 and s["a"]["false_alarms"] == 1 and s["a"]["baseline_rejected"] == 1
    assert s["a"]["claimed_effects"] == {"latency": 1}
    assert s["a"]["rejected_for"] == {"coverage": 1}
    assert s["a"]["seconds_median"] == 4.0 and s["a"]["seconds_max"] == 9.0
    assert s["b"]["errors"] == 1 and s["b"]["false_alarm_rate"] is None
    md = null_suite.markdown(s, rows)
    assert "| a | 1000 | 3 | 1 | 33% | 1 | latency x1 | 4.0 | 9.0 |" in md
    assert "short: not diagnosed: too short" in md
    assert "- a: coverage x1" in md                 # why the baselines were rejected, by family


def test_suite_on_two_tiny_recordings(tmp_path):
    """End to end: two 1000-sample recordings diagnosed, a JSON and a table written (about 6 s)."""
    assert null_suite.main(["--families", "indep,hand", "--per-family", "1", "--samples", "1000",
                            "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "null_suite.json").read_text())
    assert set(doc["summary"]) == {"indep", "hand"}
    for fam, s in doc["summary"].items():
        assert s["recordings"] == 1 and s["diagnosed"] + s["errors"] == 1
        assert s["samples"] == [1000]
    for r in doc["recordings"]:
        assert r["verdict"] in ("no_gap", "explained", "partially_explained", "unexplained", "baseline_rejected")
        assert r["false_alarm"] == ((r["verdict_on_testable"] if not r["baseline_accepted"] else r["verdict"])
                                    != "no_gap")
        assert r["seconds"] > 0
    md = (tmp_path / "null_suite.md").read_text()
    assert md.startswith("| family |") and "| indep | 1000 | 1 |" in md
