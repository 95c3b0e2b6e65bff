"""The blind benchmark's shape shares (tools/blind_shapes.py): the share of a trial's noise-free
injected change that a wrong slow-offset form can follow, and the scorer line built on it."""
import json
import pathlib
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import blind_benchmark  # noqa: E402
from blind_shapes import SHAPE_CONFUSABLE, shape_shares  # noqa: E402


def _time(n=2000, dt=0.25):
    return np.arange(n) * dt


@pytest.mark.parametrize("a", [0.2, 0.5, 0.8])
def test_a_linear_drift_follows_three_a_one_minus_a_of_a_step(a):
    """A step at fraction a of the recording, an offset along a fixed direction: the drift form
    (linear in time) follows 3 a (1 - a) of its energy, the step form all of it, and a current or
    throttle that does not move with it nothing."""
    t = _time()
    rng = np.random.default_rng(1)
    aux = {"temp": 20.0 + 0.001 * t, "current": rng.uniform(0, 10, t.size), "throttle": rng.uniform(0, 1, t.size)}
    step = (t >= t[0] + a * (t[-1] - t[0])).astype(float)
    change = np.outer(step, [0.3, -0.2, 0.5]) + 7.0                  # a constant goes to the hard iron
    s = shape_shares(t, aux, change)
    assert s["hard_iron_drift"] == pytest.approx(3 * a * (1 - a), abs=0.01)
    assert s["hard_iron_step"] > 0.97
    assert s["current_hard_iron"] < 0.01 and s["throttle_hard_iron"] < 0.01


def test_a_temperature_offset_through_a_lag_is_followed_by_the_temperature_form():
    """The temperature form reads the temp column through its thermal lags: an offset following
    the temperature through a 40 s lag is followed almost wholly; white noise is not."""
    from mkc_stream.sim.effects.base import first_order_lag

    t = _time(4000, 0.1)
    temp = 20.0 + 5.0 * (t > 100.0) + 3.0 * np.sin(t / 50.0)
    lagged = first_order_lag(t, temp, 40.0)
    s = shape_shares(t, {"temp": temp}, np.outer(lagged, [1.0, 0.5, -0.2]))
    assert s["temperature_offset"] > 0.99
    assert "current_hard_iron" not in s and "throttle_hard_iron" not in s   # no such columns
    noise = np.random.default_rng(2).normal(size=(t.size, 3))
    assert shape_shares(t, {"temp": temp}, noise)["temperature_offset"] < 0.01


def test_a_change_that_does_not_line_up_with_the_recording_has_no_shares():
    t = _time(100)
    assert shape_shares(t, {}, np.ones((99, 3))) == {}                  # a clock effect dropped rows
    bad = np.zeros((100, 3))
    bad[5, 1] = np.nan
    assert shape_shares(t, {}, bad) == {}
    assert shape_shares(t, {}, np.ones((100, 3))) == {}                 # a constant: nothing to share


def test_a_blind_trials_label_carries_its_shares():
    """A step trial of the independent simulator: its own form follows it, and the label says
    how much the drift and temperature forms follow."""
    rec, label = blind_benchmark.make_trial("single", "hard_iron_step", 4243, "indep")
    s = label["shape_share"]
    assert s["hard_iron_step"] > 0.95
    assert set(s) >= {"hard_iron_drift", "temperature_offset", "current_hard_iron", "throttle_hard_iron"}
    assert all(0.0 <= v <= 1.0 for v in s.values())


def _result(verdict, selected, shrinks):
    return {"verdict": verdict, "selected": selected, "ambiguous_with": [], "seconds": 1.0,
            "effects": [{"name": n, "shrink": s, "magnitude": {"value": 1.0}, "shrink_given_selected": 0.0}
                        for n, s in shrinks.items()]}


def test_the_shape_separable_line_leaves_out_only_the_wrong_forms_that_share_the_truths_shape(tmp_path):
    """t0: a drift that follows 0.6 of the step closes 0.7 of its gap: out of the shape-separable
    line, still in the line outside the declared pair. t1: a drift that follows 0.1 and closes 0.5
    counts in both. t2: a run without shares gives no shape-separable value."""
    (tmp_path / "sealed").mkdir()
    (tmp_path / "results").mkdir()
    single = {"kind": "single", "oracle_snr": 50.0, "magnitude": {"value": 1.0}, "truth": "hard_iron_step"}
    labels = {"t0": {**single, "shape_share": {"hard_iron_step": 1.0, "hard_iron_drift": 0.6}},
              "t1": {**single, "shape_share": {"hard_iron_step": 1.0, "hard_iron_drift": 0.1}},
              "t2": dict(single)}
    res = _result("explained", ["hard_iron_step"], {"hard_iron_step": 1.0, "hard_iron_drift": 0.7,
                                                    "colored_noise": 0.9})
    res1 = _result("explained", ["hard_iron_step"], {"hard_iron_step": 1.0, "hard_iron_drift": 0.5})
    (tmp_path / "sealed" / "labels.json").write_text(json.dumps(labels))
    for name, r in (("t0", res), ("t1", res1), ("t2", res)):
        (tmp_path / "results" / f"{name}.json").write_text(json.dumps(r))
    S, rows = blind_benchmark.step_score(tmp_path)
    assert SHAPE_CONFUSABLE == 0.3
    assert [r["best_wrong_unpaired_det"] for r in rows] == [0.7, 0.5, 0.7]
    assert rows[0]["best_wrong_shape_separable_det"] is None and rows[0]["wrong_shape_confusable"] == ["hard_iron_drift"]
    assert rows[1]["best_wrong_shape_separable_det"] == 0.5 and rows[1]["wrong_shape_confusable"] == []
    assert rows[2]["best_wrong_shape_separable_det"] is None
    assert S["best_wrong_deterministic_without_declared_partner_le_0.3"] == 0.0
    assert S["best_wrong_deterministic_shape_separable_le_0.3"] == 0.0     # t1 only: it fails
    assert S["best_wrong_over_0.3_shape_confusable"] == 1                   # t0


def test_named_first_is_split_by_whether_a_wrong_form_shares_the_truths_shape(tmp_path):
    """t0: a drift that follows 0.6 of the step is named first, the step listed ambiguous: a
    confusable trial, not named first but in the set. t1: named first, separable. t2: a drift
    that follows 0.1 named first: a separable miss. t3: no shares, named first: in the line as
    written only."""
    (tmp_path / "sealed").mkdir()
    (tmp_path / "results").mkdir()
    single = {"kind": "single", "oracle_snr": 50.0, "magnitude": {"value": 1.0}, "truth": "hard_iron_step"}
    far = {"hard_iron_step": 1.0, "hard_iron_drift": 0.1}
    labels = {"t0": {**single, "shape_share": {"hard_iron_step": 1.0, "hard_iron_drift": 0.6}},
              "t1": {**single, "shape_share": far}, "t2": {**single, "shape_share": far}, "t3": dict(single)}
    step_first = _result("explained", ["hard_iron_step"], {"hard_iron_step": 1.0, "hard_iron_drift": 0.2})
    drift_first = _result("explained", ["hard_iron_drift"], {"hard_iron_step": 0.9, "hard_iron_drift": 1.0})
    results = {"t0": {**drift_first, "ambiguous_with": ["hard_iron_step"]}, "t1": step_first,
               "t2": drift_first, "t3": step_first}
    (tmp_path / "sealed" / "labels.json").write_text(json.dumps(labels))
    for name, r in results.items():
        (tmp_path / "results" / f"{name}.json").write_text(json.dumps(r))
    S, _ = blind_benchmark.step_score(tmp_path)
    assert S["named_first"] == 0.5                                          # t1, t3 of four
    assert (S["shape_separable_trials"], S["shape_confusable_trials"]) == (2, 1)
    assert S["named_first_shape_separable"] == 0.5                          # t1 of t1, t2
    assert S["named_first_per_effect_shape_separable"] == {"hard_iron_step": 0.5}
    assert S["named_first_shape_confusable"] == 0.0
    assert S["named_first_or_ambiguous_shape_confusable"] == 1.0            # t0 lists the step


def test_a_run_generated_without_shares_gets_them_back_only_if_its_recordings_regenerate(tmp_path):
    """--step shapes regenerates each trial from its seed: the same recording gets its shares; a
    recording that differs (a changed generator) stops the step and leaves the labels alone."""
    args = ["--simulator", "indep", "--trials", "60", "--index", "11", "--out", str(tmp_path)]
    blind_benchmark.main(args + ["--step", "generate"])
    path = tmp_path / "sealed" / "labels.json"
    labels = json.loads(path.read_text())
    want = labels["trial0011"].pop("shape_share")
    path.write_text(json.dumps(labels))
    blind_benchmark.main(args + ["--step", "shapes"])
    assert json.loads(path.read_text())["trial0011"]["shape_share"] == want
    labels["trial0011"].pop("shape_share", None)
    path.write_text(json.dumps(labels))
    csv = tmp_path / "recordings" / "trial0011.csv"
    lines = csv.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln and ln[0].isdigit())
    cells = lines[i].split(",")
    cells[1] = str(float(cells[1]) + 0.5)                               # mx of the first row
    lines[i] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(SystemExit, match="differs from the one on disk"):
        blind_benchmark.main(args + ["--step", "shapes"])
    assert "shape_share" not in json.loads(path.read_text())["trial0011"]
