"""The blind benchmark (tools/blind_benchmark.py): CI runs a small fixed subset; the full run
(`python tools/blind_benchmark.py --trials 120 --jobs 2`) is marked slow.

Labels are made by the generator and only compared after each diagnosis has returned; the
diagnoser gets the recording (and, for a "removed" trial, its restricted library)."""
import importlib.util
import pathlib

import pytest

from mkc_stream.diagnose import diagnose

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("blind_benchmark", ROOT / "tools" / "blind_benchmark.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


CI_TRIALS = [("none", None, 7919), ("single", "current_hard_iron", 15838), ("single", "hard_iron_step", 23757),
             ("removed", "hard_iron_step", 55433)]


@pytest.mark.parametrize("kind,effect,seed", CI_TRIALS)
def test_blind_subset(kind, effect, seed):
    bench = _bench()
    rec, label = bench.make_trial(kind, effect, seed)
    d = diagnose(rec, exclude=label["exclude"], replicas=24)      # the label stays here, unread
    if kind == "none":
        assert d.verdict == "no_gap"
    elif kind == "single":
        assert d.selected and d.selected[0] == label["truth"]
        r = {e.name: e for e in d.effects}[label["truth"]]
        assert r.shrink >= 0.7
        assert r.magnitude["value"] == pytest.approx(label["magnitude"]["value"], rel=0.2)
    else:
        assert d.verdict in ("unexplained", "partially_explained")


@pytest.fixture(scope="module")
def full_score(tmp_path_factory):
    bench = _bench()
    out = tmp_path_factory.mktemp("blind120")
    bench.main(["--trials", "120", "--out", str(out), "--jobs", "2"])
    return bench.step_score(out)[0]


@pytest.mark.slow
def test_blind_benchmark_full(full_score):
    """The measured run (README): the acceptance lines it meets, at the issue's thresholds."""
    S = full_score
    assert S["false_alarm_rate"] <= 0.05
    assert S["named_first"] >= 0.9
    assert S["shrink_correct_ge_0.7"] >= 0.9
    assert S["removed_unexplained_or_partial"] >= 0.7 and S["removed_wrong_claimed"] <= 0.2
    assert S["magnitude_rel_error_median"] <= 0.2
    assert S["seconds_median"] <= 60


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="not met yet (issue 6 stays open): with magnitudes over the issue's whole "
                                       "realistic ranges, named first per effect >= 80% fails for hard_iron_drift 1/2, "
                                       "colored_noise 2/4, bias_random_walk 3/4, latency 3/4 (overall 60/65 = 92.3%, "
                                       "met); pair coverage 9/14 = 64% (three small thermal offsets under a ramp: their "
                                       "oracle SNR 4.6-9.4 is mostly the dip channel's, with the magnetometer's noise "
                                       "alone, not the ~0.03 rad the motion's linear acceleration adds; the norm "
                                       "channel's oracle SNR is 2.3-3.9); best wrong effect <= 0.3 in 41%; each "
                                       "measured against 90%; strict, so it fails loudly once they are met")
def test_blind_benchmark_unmet_lines(full_score):
    S = full_score
    assert min(S["named_first_per_effect"].values()) >= 0.8
    assert S["pair_truth_in_set"] >= 0.9 and S["best_wrong_le_0.3"] >= 0.9
