"""The blind benchmark's pooled score (tools/blind_benchmark.py --step pool): several runs scored as
one, on fabricated runs (no diagnosis)."""
import json
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import blind_benchmark  # noqa: E402

STEP = {"kind": "single", "oracle_snr": 50.0, "magnitude": {"value": 1.0}, "truth": "hard_iron_step",
        "shape_share": {"hard_iron_step": 1.0, "hard_iron_drift": 0.1}}
REMOVED = {"kind": "removed", "oracle_snr": 50.0, "magnitude": {"value": 1.0}, "truth": "hard_iron_step"}


def _result(verdict, selected, shrinks):
    return {"verdict": verdict, "selected": selected, "ambiguous_with": [], "seconds": 1.0,
            "effects": [{"name": n, "shrink": s, "magnitude": {"value": 1.0}, "shrink_given_selected": 0.0}
                        for n, s in shrinks.items()]}


def _run(path, trials):
    """A run directory as the benchmark leaves it: sealed labels and one result per trial."""
    (path / "sealed").mkdir(parents=True)
    (path / "results").mkdir()
    (path / "sealed" / "labels.json").write_text(json.dumps({n: lab for n, (lab, _) in trials.items()}))
    for n, (_, res) in trials.items():
        (path / "results" / f"{n}.json").write_text(json.dumps(res))
    return path


@pytest.fixture
def two_runs(tmp_path):
    """Run a: its step named first, its removed step unexplained. Run b: its step named a drift,
    its removed step explained by a drift (a wrong claim). Both name their trials alike."""
    step_first = _result("explained", ["hard_iron_step"], {"hard_iron_step": 1.0, "hard_iron_drift": 0.2})
    drift_first = _result("explained", ["hard_iron_drift"], {"hard_iron_step": 0.9, "hard_iron_drift": 1.0})
    a = _run(tmp_path / "a", {"t0": (STEP, step_first),
                              "t1": (REMOVED, _result("unexplained", [], {"hard_iron_drift": 0.1}))})
    b = _run(tmp_path / "b", {"t0": (STEP, drift_first),
                              "t1": (REMOVED, _result("explained", ["hard_iron_drift"], {"hard_iron_drift": 0.9}))})
    return a, b


def test_pooled_lines_count_every_runs_trials(two_runs, tmp_path):
    a, b = two_runs
    Sa, _ = blind_benchmark.step_score(a)
    assert (Sa["named_first"], Sa["removed_wrong_claimed"]) == (1.0, 0.0)
    S, rows = blind_benchmark.step_pool([a, b], tmp_path / "pooled")
    assert [r["trial"] for r in rows] == ["a/t0", "a/t1", "b/t0", "b/t1"]
    assert S["named_first"] == 0.5 and S["named_first_shape_separable"] == 0.5
    assert S["removed_unexplained_or_partial"] == 0.5 and S["removed_wrong_claimed"] == 0.5
    assert S["counts"]["single_typical"] == 2 and S["counts"]["removed"] == 2
    assert S["counts"]["single_typical_per_effect"] == {"hard_iron_step": 2}
    written = json.loads((tmp_path / "pooled" / "pooled_score.json").read_text())
    assert written["summary"]["named_first"] == 0.5 and len(written["rows"]) == 4


def test_pool_from_the_command_line_and_its_errors(two_runs, tmp_path, capsys):
    a, b = two_runs
    blind_benchmark.main(["--step", "pool", "--runs", str(a), str(b), "--out", str(tmp_path / "p")])
    assert json.loads(capsys.readouterr().out)["counts"]["removed"] == 2
    with pytest.raises(SystemExit):
        blind_benchmark.main(["--step", "pool", "--out", str(tmp_path / "p")])
    assert "needs --runs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        blind_benchmark.main(["--step", "pool", "--runs", str(a), str(tmp_path / "nothing"), "--out", str(tmp_path / "p")])
    assert "no sealed/labels.json" in capsys.readouterr().err
    (b / "results" / "t1.json").unlink()                  # a run whose diagnosis did not finish
    with pytest.raises(SystemExit):
        blind_benchmark.main(["--step", "pool", "--runs", str(a), str(b), "--out", str(tmp_path / "p")])
    assert "trial t1 has no result" in capsys.readouterr().err
