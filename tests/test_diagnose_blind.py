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


# The two single trials (about 35 s each) run with --runslow only: CI names a step first end to end in
# test_diagnose_verdict.py and a current first, with its magnitude, in test_diagnose.py; the null and
# the removed-effect trials have no faster end-to-end test, so CI keeps them here.
CI_TRIALS = [("none", None, 7919),
             pytest.param("single", "current_hard_iron", 15838, marks=pytest.mark.slow),
             pytest.param("single", "hard_iron_step", 23757, marks=pytest.mark.slow),
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
    """The measured run (docs/benchmarks.md, blind benchmark): the acceptance lines it meets, at their thresholds."""
    S = full_score
    assert S["false_alarm_rate"] <= 0.05
    assert S["named_first"] >= 0.9
    assert min(S["named_first_per_effect"].values()) >= 0.8
    assert S["shrink_correct_ge_0.7"] >= 0.9
    assert S["pair_truth_in_set"] >= 0.9
    assert S["removed_unexplained_or_partial"] >= 0.7
    assert S["removed_wrong_claimed"] <= 0.2
    assert S["magnitude_rel_error_median"] <= 0.2
    assert S["seconds_median"] <= 60
    # The best-wrong line, in the two readings that replaced "best wrong effect <= 0.3 in 90%" (a
    # catch-all noise model closes most of any large gap by widening its replicas, and the truth's
    # declared confusable partner closes much of it by design; docs/decisions/0014): what a wrong
    # effect adds on top of the selected ones, and the best wrong deterministic effect outside the
    # declared pair. The old reading stays in the score (best_wrong_le_0.3), reported, not a line.
    assert S["best_wrong_given_selected_le_0.3"] >= 0.9
    assert S["best_wrong_deterministic_without_declared_partner_le_0.3"] >= 0.85
    # and leaving out too the wrong forms that follow >= 0.3 of the truth's noise-free change
    # (docs/decisions/0031): reported beside it, held to the same figure
    assert S["best_wrong_deterministic_shape_separable_le_0.3"] >= 0.85
    # named first on the trials whose shape no wrong slow-offset form shares (docs/decisions/0033),
    # beside the line as written above
    assert S["named_first_shape_separable"] >= 0.9


def test_matched_snr_whitens_coloured_noise():
    """The oracle's SNR: white noise alone gives sum(s^2) / w^2; for AR(1) noise (phi 0.5, unit
    innovations) the whitened SNR^2 of a slow signal is sum(s^2) (1 - phi)^2 (the noise's
    spectral density near 0 is 1 / (1 - phi)^2), 3 times less than white noise of the same
    variance (1 / (1 - phi^2)) would give. The sine is periodic in the record, so no edge
    effect blurs the check."""
    import numpy as np
    from scipy.signal import lfilter

    bench = _bench()
    rng = np.random.default_rng(3)
    n = 2 ** 16
    s = np.sin(2 * np.pi * 32 * np.arange(n) / n)
    assert bench.matched_snr2(s, np.zeros(n), 0.1) == pytest.approx(np.sum(s * s) / 0.01, rel=1e-9)
    phi, e = 0.5, rng.normal(size=n)
    ar = lfilter([1.0], [1.0, -phi], e)
    # smoothing over 512 independent bins: the estimate's own scatter is ~5%
    gls = bench.matched_snr2(s, ar, 1e-6, half_width=512)
    assert gls == pytest.approx(np.sum(s * s) * (1 - phi) ** 2, rel=0.15)
    white = bench.matched_snr2(s, rng.normal(size=n) * ar.std(), 1e-6, half_width=512)
    assert white == pytest.approx(np.sum(s * s) * (1 - phi ** 2), rel=0.15)


def test_oracle_counts_the_accelerometers_direction_noise():
    """The dip channel is the field's direction against the accelerometer's: the hand motion's
    linear acceleration (0.3 m/s^2 RMS, ~1.7 deg) is noise there, so the oracle sees a slow
    hard-iron change far less well than it would with a perfect accelerometer."""
    import numpy as np

    from mkc_stream.sim import SensorModel, generate, simulate

    bench = _bench()
    snr = {}
    for lin, acc_noise in ((0.3, 0.03), (0.0, 0.0)):
        traj = generate("hand", duration=200.0, rate=20.0, seed=5, linear_acc=lin)
        sensor = SensorModel(field=45.0, noise=0.1, acc_noise=acc_noise)
        ramp = np.outer((traj.t - traj.t[0]) / (traj.t[-1] - traj.t[0]), [0.3, -0.2, 0.25])
        eff = bench.Inject("ramp", "offset", lambda ctx: ctx.m.__iadd__(ramp))
        sim = simulate(traj, sensor, effects=[(eff, {})], seed=6)
        snr[lin] = bench.oracle_snr(sim, simulate(traj, sensor, seed=6), traj, sensor)
    # 1.32 measured (2.1 before the oracle refitted the calibration on the dip channel too);
    # counting the magnetometer noise alone gives 1.0
    assert snr[0.0] > 1.2 * snr[0.3]


def test_oracle_counts_only_what_the_refitted_calibration_leaves():
    """The diagnoser refits hard iron and symmetric soft iron on the norm and dip channels at
    once, so the oracle must too: a symmetric coupling of the axes (S stays symmetric) is all
    absorbed, whatever its direction change in the dip; a rotation of the same size (which no
    symmetric S can make without changing the norm) is not. Before the joint refit the oracle
    removed the calibration from the norm channel only and gave the symmetric coupling SNR
    7.6, nearly the rotation's 8.3."""
    import numpy as np

    from mkc_stream.sim import SensorModel, generate, simulate

    bench = _bench()
    traj = generate("hand", duration=200.0, rate=20.0, seed=5, linear_acc=0.3)
    sensor = SensorModel(field=45.0, noise=0.1, acc_noise=0.03, soft_iron=np.eye(3))
    clean = simulate(traj, sensor, seed=6)
    a = np.radians(1.0)
    snr = {}
    for kind, K in (("symmetric", np.array([[0, a, 0], [a, 0, -a], [0, -a, 0]])),
                    ("rotation", np.array([[0, a, 0], [-a, 0, -a], [0, a, 0]]))):
        eff = bench.Inject(kind, "field", lambda ctx, K=K: ctx.B.__setitem__(slice(None), ctx.B @ (np.eye(3) + K).T))
        snr[kind] = bench.oracle_snr(simulate(traj, sensor, effects=[(eff, {})], seed=6), clean, traj, sensor)
    assert snr["rotation"] > 5.0
    assert snr["symmetric"] < 0.05 * snr["rotation"]


def _result(verdict, selected, shrinks):
    return {"verdict": verdict, "selected": selected, "ambiguous_with": [], "seconds": 1.0,
            "effects": [{"name": n, "shrink": s, "magnitude": {"value": 1.0}, "shrink_given_selected": 0.0}
                        for n, s in shrinks.items()]}


def test_score_splits_the_best_wrong_line_by_source(tmp_path):
    """The scorer says what the best-wrong failures are made of: a catch-all noise model, the
    truth's declared confusable partner, or another effect (fabricated results, no diagnosis)."""
    import json

    bench = _bench()
    (tmp_path / "sealed").mkdir()
    (tmp_path / "results").mkdir()
    single = {"kind": "single", "oracle_snr": 50.0, "magnitude": {"value": 1.0}}
    labels = {"t0": {**single, "truth": "current_hard_iron"}, "t1": {**single, "truth": "current_hard_iron"},
              "t2": {**single, "truth": "latency"}, "t3": {**single, "truth": "hard_iron_step"},
              "t4": {"kind": "none", "truth": None}}
    results = {
        "t0": _result("explained", ["current_hard_iron"], {"current_hard_iron": 1.0, "colored_noise": 0.9,
                                                           "throttle_hard_iron": 0.2, "temperature_offset": 0.05}),
        "t1": _result("explained", ["current_hard_iron"], {"current_hard_iron": 1.0, "throttle_hard_iron": 0.95,
                                                           "colored_noise": 0.1, "hysteresis": 0.1}),
        "t2": _result("explained", ["latency"], {"latency": 1.0, "hysteresis": 0.5, "colored_noise": 0.4}),
        "t3": _result("explained", ["hard_iron_step"], {"hard_iron_step": 1.0, "temperature_offset": 0.1}),
        "t4": _result("no_gap", [], {"latency": None}),
    }
    (tmp_path / "sealed" / "labels.json").write_text(json.dumps(labels))
    for name, r in results.items():
        (tmp_path / "results" / f"{name}.json").write_text(json.dumps(r))
    S, rows = bench.step_score(tmp_path)
    assert S["best_wrong_le_0.3"] == 0.25
    assert S["best_wrong_over_0.3_by_source"] == {"catch_all": 1, "declared_partner": 1, "other": 1}
    assert S["best_wrong_without_declared_partner_le_0.3"] == 0.5       # t1's partner left out, t0's noise kept
    assert S["best_wrong_deterministic_le_0.3"] == 0.5                  # t0 passes without its catch-all
    assert S["best_wrong_deterministic_without_declared_partner_le_0.3"] == 0.75     # t0 and t1 pass
    assert [r.get("best_wrong_name") for r in rows[:4]] == ["colored_noise", "throttle_hard_iron", "hysteresis",
                                                             "temperature_offset"]


def test_score_leaves_a_form_containing_the_truth_out_of_the_lines_outside_the_pair(tmp_path):
    """sensor_compression's odd terms are scale_nonlinearity's columns (MeanForm.contains): on a
    scale_nonlinearity trial it closes what the truth closes. The lines "outside the declared
    pair" leave it out, as they leave out the truth's partner; the all-wrong line keeps it."""
    import json

    bench = _bench()
    assert bench.CONTAINERS["scale_nonlinearity"] == {"sensor_compression"}
    (tmp_path / "sealed").mkdir()
    (tmp_path / "results").mkdir()
    single = {"kind": "single", "oracle_snr": 50.0, "magnitude": {"value": 1.0}}
    labels = {"t0": {**single, "truth": "scale_nonlinearity"}, "t1": {**single, "truth": "sensor_compression"}}
    results = {
        "t0": _result("explained", ["scale_nonlinearity"], {"scale_nonlinearity": 1.0, "sensor_compression": 0.98,
                                                            "higher_order_soft_iron": 0.1}),
        # the other way round the special case is an effect of its own: it counts
        "t1": _result("explained", ["sensor_compression"], {"sensor_compression": 1.0, "scale_nonlinearity": 0.6}),
    }
    (tmp_path / "sealed" / "labels.json").write_text(json.dumps(labels))
    for name, r in results.items():
        (tmp_path / "results" / f"{name}.json").write_text(json.dumps(r))
    S, rows = bench.step_score(tmp_path)
    assert rows[0]["best_wrong_source"] == "contains_truth" and rows[0]["best_wrong_unpaired_det"] == 0.1
    assert rows[1]["best_wrong_unpaired_det"] == 0.6
    assert S["best_wrong_deterministic_le_0.3"] == 0.0
    assert S["best_wrong_deterministic_without_declared_partner_le_0.3"] == 0.5
