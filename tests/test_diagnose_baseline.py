"""The diagnosis's baseline knows what the recording can tell.

* the inclination is reported in the geomagnetic convention (below the horizontal, positive
  down), not as the model's field-to-specific-force angle;
* a baseline calibration the calibrator would reject is reported as rejected, with the
  calibrator's structured reason, and no gap is read from it: the verdict is
  "baseline_rejected" and says what was still tested (raw values, timestamps);
* statistics and effects that need a calibration or orientations the recording lacks are "not
  testable", with the reason, never a gap.
"""
import json

import numpy as np
import pytest

from mkc_stream.diagnose import diagnose, report
from mkc_stream.diagnose.baseline import fit_baseline, inclination_deg
from mkc_stream.diagnose.frame import prepare
from mkc_stream.diagnose.gap import GapIndex
from mkc_stream.diagnose.scope import CALIBRATION_FREE_EFFECTS, CALIBRATION_FREE_FAMILIES, Scope
from mkc_stream.sim import SensorModel, generate, simulate
from mkc_stream.sim.effects import EFFECTS
from mkc_stream.sim.effects.base import Evidence


@pytest.mark.parametrize("inclination", [60.0, -40.0])
def test_baseline_reports_the_inclination_below_the_horizontal_positive_down(inclination):
    traj = generate("hand", duration=120, rate=20, seed=5, inclination=inclination)
    rec = simulate(traj, SensorModel(noise=0.1), seed=6).recording
    base = fit_baseline(prepare(rec, 10_000))
    assert base.scope.accepted, base.scope.reason
    assert inclination_deg(base.fit.state.dip0) == pytest.approx(inclination, abs=1.0)


def _evidence(coverage):
    return Evidence(n=5000, duration=200.0, rate=25.0, aux_span={"current": 20.0, "temp": 5.0, "throttle": 0.8, "voltage": 1.0}, has_acc=True,
                    has_gyro=True, coverage=coverage, rotation_rate=1.0, timestamps_real=True)


def _rejected():
    from mkc_stream.calib.acceptance import AcceptanceRules, evaluate

    q = {"coverage": 0.22, "condition": 14.0, "outlier_fraction": 0.01, "residual_rms": 0.1}
    rej = evaluate(q, 50.0, "uT", AcceptanceRules())
    return Scope(accepted=False, rejection=rej, coverage=0.21, quality=q)


def test_a_rejected_calibration_leaves_only_the_calibration_free_statistics_and_effects():
    scope = _rejected()
    assert "coverage" in scope.rejection.failed
    for fam in ("distribution/norm", "aux:current/norm", "time/dip", "changes/norm", "quartic/norm"):
        why = scope.family_reason(fam)
        assert why is not None and "sphere coverage 22% < 50%" in why
    for fam in CALIBRATION_FREE_FAMILIES:
        assert scope.family_reason(fam) is None
    ev = _evidence(0.21)
    for name, eff in EFFECTS.items():
        ok, why = scope.effect_testable(eff, ev)
        if name in CALIBRATION_FREE_EFFECTS:
            assert ok, (name, why)
        else:
            assert not ok and ("calibrat" in why or "sphere" in why), (name, why)


def test_coverage_families_need_the_coverage_of_the_effect_they_stand_for():
    low = Scope(accepted=True, coverage=0.4)
    assert "40%" in low.family_reason("quartic/norm")
    assert low.family_reason("sphere/norm") is None and low.family_reason("aux:temp/norm") is None
    assert Scope(accepted=True, coverage=0.8).family_reason("quartic/norm") is None


def test_a_family_left_out_does_not_move_the_gap_index():
    fams = ["sphere"] * 30 + ["quartic"] * 30
    chans = ["norm"] * 60
    w = np.ones(60)
    z_quiet = np.r_[np.full(30, 0.5), np.full(30, 0.5)]
    z_loud = np.r_[np.full(30, 0.5), np.full(30, 20.0)]
    on = GapIndex(fams, chans)
    assert on.index(z_loud, w) > 3 * on.index(z_quiet, w)
    off = GapIndex(fams, chans, off=lambda n: "no coverage" if n.startswith("quartic") else None)
    assert off.off == {"quartic/norm": "no coverage"}
    assert off.index(z_loud, w) == pytest.approx(off.index(z_quiet, w))
    assert np.isnan(off.family_scores(z_loud, w)[off.names.index("quartic/norm")])


@pytest.fixture(scope="module")
def level_flight():
    return generate("flight", duration=200, rate=25, seed=1, power=True)


def test_level_flight_is_a_rejected_baseline_not_a_gap(level_flight):
    rec = simulate(level_flight, SensorModel(noise=0.1, burst_fraction=0.01), seed=2).recording
    d = diagnose(rec, replicas=24)
    assert d.verdict == "baseline_rejected"
    obj = json.loads(json.dumps(d.to_json()))
    cal = obj["info"]["baseline"]["calibration"]
    assert cal["accepted"] is False and "coverage" in cal["rejection"]["failed"]
    assert cal["rejection"]["values"]["coverage"] < 0.5
    scope = obj["info"]["scope"]
    assert scope["calibration_accepted"] is False
    assert scope["verdict_on_testable"] == "no_gap"
    assert "aux:current/norm" in scope["statistics_not_testable"]
    assert all(w["family"] in CALIBRATION_FREE_FAMILIES for w in obj["where"])
    for e in obj["effects"]:
        assert e["testable"] == (e["name"] in CALIBRATION_FREE_EFFECTS), e
        assert not e["selected"]
    b = obj["info"]["baseline"]
    assert b["inclination_deg"] == pytest.approx(60.0, abs=4.0)       # the flight's field dips 60 deg
    assert "positive downward" in b["inclination_convention"]
    txt = report.text(d)
    assert "BASELINE REJECTED" in txt and "sphere coverage" in txt and "UNEXPLAINED" not in txt
    assert "still tested" in txt and "no gap there" in txt


def test_a_rejected_baseline_still_tests_the_raw_values(level_flight):
    rec = simulate(level_flight, SensorModel(noise=0.1, burst_fraction=0.01), seed=2,
                   effects=[("quantization", {"lsb": 0.3})]).recording
    d = diagnose(rec, replicas=24)
    assert d.verdict == "baseline_rejected"
    assert d.info["scope"]["verdict_on_testable"] == "explained"
    assert d.selected == ["quantization"]
    q = next(r for r in d.effects if r.name == "quantization")
    assert q.magnitude["value"] == pytest.approx(0.3, rel=0.05)
    assert "explained by quantization" in report.headline(d)


def test_an_inclination_outside_the_angle_range_is_not_determined():
    """The angle between the field and the specific force lies in 0-180 deg; a baseline fit that put
    its constant at -40 deg (a flight log whose calibration the calibrator rejects) reported
    "inclination -130.2 deg". Now it is not determined, and the report says so."""
    import math

    from mkc_stream.diagnose.report import _inclination_text

    assert inclination_deg(math.radians(150.0)) == pytest.approx(60.0)
    assert math.isnan(inclination_deg(math.radians(-40.2)))
    assert math.isnan(inclination_deg(math.radians(181.0)))
    text = _inclination_text({"inclination_deg": float("nan"), "field_gravity_angle_deg": -40.2})
    assert "not determined" in text and "-40.2" in text
    assert "inclination 60.0 deg" in _inclination_text({"inclination_deg": 60.0, "field_gravity_angle_deg": 150.0})
    assert _inclination_text({"inclination_deg": None, "field_gravity_angle_deg": None}) == ""


def test_samples_that_give_no_ellipsoid_are_a_rejected_baseline_not_an_error(level_flight, monkeypatch):
    """When the baseline fit finds no ellipsoid (a real bag and a px4log whose quadric was
    indefinite), the diagnosis used to stop with an error. It is a rejected baseline with that
    reason around a sphere stand-in, and what needs no calibration is still tested: here the
    0.3 uT rounding of the values."""
    from mkc_stream.calib import fit as fit_module
    from mkc_stream.calib.ellipsoid import EllipsoidError

    def no_ellipsoid(*args, **kwargs):
        raise EllipsoidError("the fitted quadric is not an ellipsoid: A is indefinite")

    rec = simulate(level_flight, SensorModel(noise=0.1, burst_fraction=0.01), seed=2,
                   effects=[("quantization", {"lsb": 0.3})]).recording
    monkeypatch.setattr(fit_module, "fit_ellipsoid", no_ellipsoid)
    d = diagnose(rec, replicas=24)
    assert d.verdict == "baseline_rejected"
    cal = d.to_json()["info"]["baseline"]["calibration"]
    assert cal["accepted"] is False and cal["rejection"]["code"] == "not_ellipsoid"
    assert "no ellipsoid" in cal["reason"] and "indefinite" in cal["reason"]
    assert d.info["scope"]["verdict_on_testable"] == "explained" and d.selected == ["quantization"]
    q = next(r for r in d.effects if r.name == "quantization")
    assert q.magnitude["value"] == pytest.approx(0.3, rel=0.05)
    assert all(not r.testable for r in d.effects if r.name not in CALIBRATION_FREE_EFFECTS)
    assert "BASELINE REJECTED" in report.text(d)
