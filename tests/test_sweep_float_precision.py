"""tools/sweep_float_precision.py: the float builds against the double reference over many streams.

The figures of one stream (compare) and of a sweep (summarise) on records made here, then the tool
end to end on two streams through the host harness (needs make and a C compiler).
"""
from __future__ import annotations

import json
import pathlib
import shutil
import sys

import numpy as np
import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT / "tools"))

import replay_harness as RH  # noqa: E402
import sweep_float_precision as SW  # noqa: E402


def records(n: int = 4) -> np.ndarray:
    """n accepted checkpoints 32 samples apart with a plausible calibration (F = 50)."""
    r = np.zeros((n, RH.RECORD))
    r[:, RH.O_SEEN] = 32.0 * (np.arange(n) + 1)
    r[:, RH.O_ESTEPS] = np.arange(n) + 1
    r[:, RH.O_ACCEPTED] = 1.0
    r[:, RH.O_THETA:RH.O_THETA + 9] = np.linspace(-1.0, 2.0, 9)
    r[:, RH.O_HARD:RH.O_HARD + 3] = [5.0, -3.0, 20.0]
    r[:, RH.O_SOFT:RH.O_SOFT + 9] = np.eye(3).reshape(-1)
    r[:, RH.O_FIELD] = 50.0
    return r


def test_compare_finds_the_first_departing_checkpoint_and_its_size():
    ref = records()
    other = ref.copy()
    other[2, RH.O_THETA + 4] += 3e-4 * 2.0          # 3e-4 of max |theta| = 2
    other[3, RH.O_HARD + 1] += 0.5                  # 1e-2 of F
    got = SW.compare(other, ref)
    assert got["first_beyond_checkpoint"] == 2
    assert got["checkpoints_beyond"] == 1           # theta departs at 2 only; b at 3 counts in worst
    assert got["theta"] == pytest.approx(3e-4)
    assert got["b"] == pytest.approx(1e-2)
    assert got["worst"] == pytest.approx(1e-2)
    assert got["same_decisions"] and got["accepted"] == 4
    assert not got["cold_start_there"]


def test_compare_pairs_by_samples_when_a_build_takes_another_checkpoint():
    ref = records(5)
    other = np.delete(ref, 1, axis=0)               # the float build skipped checkpoint 1
    got = SW.compare(other, ref)
    assert not got["same_decisions"]
    assert got["accepted"] == 4 and got["worst"] == 0.0


def test_a_departure_after_a_cold_start_is_marked():
    ref = records()
    ref[2:, RH.O_ESTEPS] += 10                      # checkpoint 2 ran a cold start (11 E-steps)
    other = ref.copy()
    other[2, RH.O_THETA] += 1e-3
    assert SW.compare(other, ref)["cold_start_there"]


def test_summary_counts_departures_and_accuracy_both_ways():
    rows = [{"worst": w, "same_decisions": s, "cold_start_there": c, "truth_error_reference": er,
             "truth_error_other": eo}
            for w, s, c, er, eo in [(1e-5, True, False, 1e-3, 1e-3), (2e-4, True, True, 1e-3, 1.2e-3),
                                    (5e-2, False, True, 1e-3, 3e-2), (3e-3, True, False, 2e-2, 1e-3),
                                    (0.0, True, False, float("nan"), float("nan"))]]
    s = SW.summarise(rows)
    assert s["streams"] == 5 and s["decisions_differ"] == 1
    assert s["beyond_0.0001"] == 3 and s["beyond_0.001"] == 2
    assert s["beyond_1e-4_after_a_cold_start"] == 2
    assert s["compared_for_accuracy"] == 4
    assert s["other_worse_by_1e-3"] == 1 and s["other_better_by_1e-3"] == 1
    assert s["truth_error_largest_increase"] == pytest.approx(2.9e-2)
    assert s["truth_error_largest_decrease"] == pytest.approx(1.9e-2)


@pytest.mark.skipif(shutil.which("make") is None, reason="no `make` on PATH")
def test_the_sweep_runs_end_to_end_on_the_host(tmp_path, capsys):
    out = tmp_path / "sweep.json"
    assert SW.main(["--streams", "2", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["compared"] == "floatonly on host"
    assert [(r["seed"], r["burst"]) for r in d["streams"]] == [(100, 0.10), (100, 0.25)]
    for r in d["streams"]:
        assert r["accepted"] > 10                   # both builds accept most checkpoints of 3000 samples
        assert 0.0 <= r["worst"] < 1e-2             # a float build, not another calibration
        # a synthetic stream's calibration is within a few per cent of the field from the truth
        assert 0.0 < r["truth_error_reference"] < 5e-2 and 0.0 < r["truth_error_other"] < 5e-2
    assert "2 streams: decisions differ in" in capsys.readouterr().out
