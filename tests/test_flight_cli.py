"""`mkc-stream calibrate LOG`: the attitude-aided fit by default for a log with attitude and position."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mkc_stream.cli import main
from mkc_stream.flight.simulated import simulated_flight
from mkc_stream.io.recording import write_recording

pytest.importorskip("pygeomag", reason='the Earth-field model needs pip install "mkc-stream[wmm]"')

LAT, LON, ALT, DATE = 47.4, 8.5, 500.0, "2026-07-02"


@pytest.fixture(scope="module")
def flight_csv(tmp_path_factory):
    """A 300 s simulated level flight with turns, its field from WMM2025 at (LAT, LON) on DATE."""
    from mkc_stream.flight.earthfield import earth_field

    ef = earth_field(LAT, LON, ALT, DATE)
    f = simulated_flight(seed=2, h_ned=tuple(ef.ned_uT), pitch_amp=0.25, bank_gain=25.0, duration=300.0, rate=20.0)
    rec = f.recording
    aux = dict(rec.aux)
    aux.update(lat=np.full(rec.t.shape, LAT), lon=np.full(rec.t.shape, LON), alt=np.full(rec.t.shape, ALT))
    path = tmp_path_factory.mktemp("flight") / "flight.csv"
    write_recording(path, rec.t, rec.mag, aux, {"units.mag": "uT", "date": DATE})
    return path, f.truth


def run(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_a_flight_log_is_calibrated_against_the_earth_field(flight_csv, capsys):
    path, truth = flight_csv
    code, out, _ = run(["calibrate", str(path), "--json", "-", "--quiet"], capsys)
    obj = json.loads(out)
    assert code == 0 and obj["status"] == "accepted" and obj["method"] == "mkc-em-attitude"
    err = np.array(obj["hard_iron"]) - truth["b"]
    # the level flight pins the horizontal hard iron; z also carries the tilt error of the logged
    # attitude times the vertical field (0.50 uT measured, docs/flight.md)
    assert np.linalg.norm(err[:2]) < 0.3 and abs(err[2]) < 1.0
    assert obj["earth_field"]["model"] == "WMM2025"
    comp = obj["compensation"]
    assert np.allclose(comp["current"], truth["K"], atol=0.02) and comp["current_unit"] == "uT/A"
    # the 95% interval is the coefficient's uncertainty: the truth lies within 3 half-widths on every axis
    ci = np.array(comp["current_ci"])
    assert np.all(np.abs(np.array(comp["current"]) - truth["K"]) <= 1.5 * (ci[:, 1] - ci[:, 0]))


def test_the_same_flight_fails_the_sphere_fit_it_would_otherwise_get(flight_csv, capsys):
    path, _ = flight_csv
    code, out, _ = run(["calibrate", str(path), "--no-attitude", "--json", "-", "--quiet"], capsys)
    obj = json.loads(out)
    assert obj["method"] != "mkc-em-attitude"
    if code == 1:                        # a level flight: too little of the sphere
        assert "coverage" in obj["rejection"]["failed"]


def test_attitude_without_an_attitude_is_a_clear_rejection(tmp_path, capsys):
    code, out, _ = run(["calibrate", "demo", "--attitude", "--json", "-", "--quiet"], capsys)
    obj = json.loads(out)
    assert code == 1 and obj["status"] == "rejected" and "attitude" in obj["reason"]
    code, _, err = run(["calibrate", "demo", "--attitude", "--lat", "47"], capsys)
    assert code == 2 and "--lat and --lon" in err


def test_the_report_names_what_was_held_and_the_earth_field(flight_csv, capsys):
    path, _ = flight_csv
    code, out, _ = run(["calibrate", str(path)], capsys)
    assert code == 0
    assert "Earth field   : WMM2025" in out and "current       :" in out and "status        : ACCEPTED" in out


def test_a_flight_calibration_goes_to_the_autopilot_with_its_current_compensation(flight_csv, tmp_path, capsys):
    from mkc_stream.params import read_params

    path, truth = flight_csv
    param = tmp_path / "compass.param"
    code, out, _ = run(["calibrate", str(path), "--json", "-", "--quiet", "--params", f"ardupilot:{param}"], capsys)
    assert code == 0
    compass = read_params("ardupilot", param)[0]
    text = param.read_text()
    assert "COMPASS_MOTCT,2" in text                      # compensation against current
    assert compass is not None and json.loads(out)["compensation"]["current"] is not None


def test_the_tilt_error_is_estimated_by_default_and_can_be_given_or_turned_off(flight_csv, capsys):
    path, _ = flight_csv
    fits = {}
    for opt in ([], ["--tilt-sd-deg", "off"], ["--tilt-sd-deg", "0.4"]):
        code, out, _ = run(["calibrate", str(path), "--json", "-", "--quiet", *opt], capsys)
        assert code == 0
        fits[" ".join(opt)] = json.loads(out)["attitude_fit"]
    assert 0.1 < fits[""]["tilt_error_sd_deg"] < 0.6            # the simulated log's is 0.3 deg
    assert fits[""]["tilt_error_sd_estimated_deg"] == fits[""]["tilt_error_sd_deg"]
    assert fits["--tilt-sd-deg off"]["tilt_error_sd_deg"] is None
    assert fits["--tilt-sd-deg 0.4"]["tilt_error_sd_deg"] == pytest.approx(0.4)
    assert fits["--tilt-sd-deg 0.4"]["tilt_error_sd_estimated_deg"] is None


@pytest.mark.parametrize("bad", ["-1", "nan", "often"])
def test_a_bad_tilt_error_is_a_usage_error(flight_csv, capsys, bad):
    path, _ = flight_csv
    code, _, err = run(["calibrate", str(path), "--tilt-sd-deg", bad], capsys)
    assert code == 2 and "--tilt-sd-deg" in err and "expected an angle" in err
