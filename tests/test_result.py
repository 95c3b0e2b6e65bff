"""One calibration result for batch, stream and the C port, with a rejection a script can test."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mkc_stream.calib.acceptance import CHECKS, evaluate
from mkc_stream.calib.fit import fit_ellipsoid
from mkc_stream.calib.result import Calibration, Rejection, no_calibration_json
from mkc_stream.calib.streaming import MagCalibrator
from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.cli import main


def single_axis_rotation(n=3000):
    ang = np.linspace(0, 30 * np.pi, n)
    return np.stack([30 * np.cos(ang), 30 * np.sin(ang), np.full_like(ang, 20.0)], 1)


def test_evaluate_names_every_failed_check_with_its_values():
    q = {"coverage": 0.3, "condition": 10.0, "outlier_fraction": 0.6, "residual_rms": 1.0}
    r = evaluate(q, 5.0, "uT")
    assert r.code == "rejected"
    assert r.failed == ("coverage", "outliers", "residual", "field_range")
    assert set(r.failed) <= set(CHECKS)
    assert r.values["coverage"] == 0.3 and r.values["residual_rel"] == pytest.approx(0.2)
    assert r.text.count(";") == 3 and "sphere coverage 30%" in r.text
    assert evaluate({"coverage": 0.9, "condition": 10.0, "outlier_fraction": 0.0, "residual_rms": 0.5}, 50.0) is None


def test_batch_and_stream_give_the_same_result_type():
    s = synthetic_mag(seed=3, N=3000, burst_fraction=0.1)
    batch = fit_ellipsoid(s.raw, "mkc-em").calibration("uT", raw=s.raw)
    cal = MagCalibrator(window=256)
    cal.update(s.raw)
    for c in (batch, cal.accepted, cal.trial):
        assert isinstance(c, Calibration)
    assert batch.accepted and batch.rejection is None and batch.method == "mkc-em"
    assert batch.uncertainty is not None and np.isfinite(batch.uncertainty["hard_iron_sd"]).all()
    assert np.allclose(batch.apply(s.raw), fit_ellipsoid(s.raw, "mkc-em").apply(s.raw))
    a, b = batch.to_json(), cal.accepted.to_json()
    assert set(a) == set(b) and "rejection" not in a


def test_a_stream_that_cannot_calibrate_says_why_in_code_and_names():
    cal = MagCalibrator(window=256)
    cal.update(single_axis_rotation())
    r = cal.status()
    assert isinstance(r, Rejection) and r.code in ("rejected", "waiting_coverage", "not_ellipsoid")
    if r.code == "rejected":
        assert "coverage" in r.failed
    assert cal.status_reason() == r.text
    obj = no_calibration_json(r, counts={"samples": 3000})
    assert obj["rejection"]["code"] == r.code and obj["reason"] == r.text and obj["hard_iron"] is None


def test_the_c_port_reports_the_same_rejection(tmp_path):
    from mkc_stream import cport as FW
    from mkc_stream.cport import CMagCalibrator

    why = FW.toolchain_problem()
    if why:
        pytest.skip(f"C port not buildable here: {why}")
    mags = single_axis_rotation()
    py, c = MagCalibrator(window=256), CMagCalibrator(window=256)
    py.update(mags)
    c.update(mags)
    rp, rc = py.status(), c.status()
    assert (rp.code, rp.failed, rp.text) == (rc.code, rc.failed, rc.text)
    s = synthetic_mag(seed=3, N=3000, burst_fraction=0.1)
    py, c = MagCalibrator(window=256), CMagCalibrator(window=256)
    py.update(s.raw)
    c.update(s.raw)
    assert isinstance(c.accepted, Calibration) and c.status() is None and py.status() is None
    assert np.abs(c.accepted.hard_iron - py.accepted.hard_iron).max() < 1e-9 * py.accepted.field


def test_cli_json_of_a_rejection_is_structured(tmp_path, capsys):
    mags = single_axis_rotation()
    path = tmp_path / "flat.csv"
    np.savetxt(path, np.column_stack([np.arange(len(mags)) * 0.02, mags]), delimiter=",",
               header="t,mx,my,mz", comments="")
    for extra in ([], ["--stream"]):
        code = main(["calibrate", str(path), "--json", "-", "--quiet", *extra])
        obj = json.loads(capsys.readouterr().out)
        assert code == 1 and obj["status"] == "rejected"
        assert obj["rejection"]["code"] in ("rejected", "waiting_coverage", "not_ellipsoid")
        assert obj["reason"]
