"""`mkc-stream calibrate LOG --stream` on a recording with attitude: the attitude-aided stream
(mkc_stream/flight/streaming.py through mkc_stream/commands/calibrate.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mkc_stream.cli import main
from mkc_stream.flight.simulated import simulated_flight
from mkc_stream.io.recording import write_recording

pytest.importorskip("pygeomag", reason='the Earth-field model needs pip install "mkc-stream[wmm]"')

LAT, LON, ALT, DATE = 47.4, 8.5, 500.0, "2026-07-02"


def _write(path, rec, aux, mag=None):
    write_recording(path, rec.t, rec.mag if mag is None else mag, aux, {"units.mag": "uT", "date": DATE})
    return path


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 300 s simulated level flight at 20 Hz, 10% disturbed, its field from WMM2025 at (LAT, LON) on
    DATE; one row without a field and one without an attitude."""
    from mkc_stream.flight.earthfield import earth_field

    ef = earth_field(LAT, LON, ALT, DATE)
    f = simulated_flight(seed=2, h_ned=tuple(ef.ned_uT), duration=300.0, rate=20.0, yaw_error_deg=0.0, disturbed=0.1)
    rec = f.recording
    aux = {k: v.copy() for k, v in rec.aux.items()}
    aux.update(lat=np.full(rec.t.shape, LAT), lon=np.full(rec.t.shape, LON), alt=np.full(rec.t.shape, ALT))
    mag = rec.mag.copy()
    mag[100] = np.nan
    aux["qw"][200] = np.nan
    d = tmp_path_factory.mktemp("flight_stream")
    no_pos = {k: v for k, v in aux.items() if k not in ("lat", "lon", "alt")}
    no_att = {k: v for k, v in aux.items() if k not in ("qw", "qx", "qy", "qz")}
    return {"log": _write(d / "flight.csv", rec, aux, mag), "no_position": _write(d / "no_pos.csv", rec, no_pos),
            "no_attitude": _write(d / "no_att.csv", rec, no_att), "truth": f.truth}


def run(argv, capsys):
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_stream_on_a_flight_gives_the_calibration_with_its_documented_fields(flight, capsys):
    truth = flight["truth"]
    code, out, _ = run(["calibrate", str(flight["log"]), "--stream", "--json", "-", "--quiet"], capsys)
    obj = json.loads(out)
    assert code == 0 and obj["status"] == "accepted" and obj["method"] == "mkc-em-attitude-stream"
    for key in ("hard_iron", "soft_iron", "field", "channels", "quality", "reason", "counts", "uncertainty",
                "compensation", "earth_field"):
        assert key in obj
    err = np.array(obj["hard_iron"]) - truth["b"]
    # the horizontal hard iron is pinned by the turns; z trades against the vertical gain in level
    # flight (measured: [-0.15, 0.15, -0.75] uT)
    assert np.linalg.norm(err[:2]) < 0.3 and abs(err[2]) < 1.0
    S = np.array(obj["soft_iron"])
    assert np.allclose(S, S.T) and abs(np.linalg.det(S) - 1.0) < 1e-9
    assert abs(obj["field"] - np.linalg.norm(truth["h_ned"])) / np.linalg.norm(truth["h_ned"]) < 0.02
    comp = obj["compensation"]
    assert np.allclose(comp["current"], truth["K"], atol=0.03) and comp["current_unit"] == "uT/A"
    assert comp["delay_s"] == 0.0 and np.array(comp["current_ci"]).shape == (3, 2)
    assert obj["earth_field"]["model"] == "WMM2025"
    assert len(obj["uncertainty"]["hard_iron_sd"]) == 3 and obj["uncertainty"]["heading_sd_deg"] > 0
    # bad rows: the reader skips the row without a field, the stream counts the one without an attitude
    assert obj["counts"]["bad_frames"] == 2 and obj["counts"]["samples"] == 5999
    assert obj["evolution"] and obj["first_accepted_at_sample"] is not None


def test_the_human_report_names_the_method_and_progress_goes_to_stderr(flight, capsys, monkeypatch):
    from mkc_stream.commands import common

    monkeypatch.setattr(common.Progress, "EVERY_S", 0.0)
    code, out, err = run(["calibrate", str(flight["log"]), "--stream"], capsys)
    assert code == 0
    assert "mkc-em-attitude-stream" in out and "used without delay" in out and "status        : ACCEPTED" in out
    assert "streaming 5999/5999 samples (100%), accepted" in err
    code, _, err = run(["calibrate", str(flight["log"]), "--stream", "--quiet"], capsys)
    assert code == 0 and "streaming" not in err


def test_params_are_written_from_the_stream_with_the_current_terms(flight, capsys, tmp_path):
    dest = tmp_path / "compass.param"
    code, _, _ = run(["calibrate", str(flight["log"]), "--stream", "--quiet", "--params", f"ardupilot:{dest}"], capsys)
    text = dest.read_text()
    assert code == 0 and "COMPASS_OFS_X" in text and "COMPASS_MOT_X" in text


def test_attitude_without_a_field_reference_is_refused_with_the_reason(flight, capsys):
    code, out, _ = run(["calibrate", str(flight["no_position"]), "--stream", "--attitude", "--json", "-", "--quiet"],
                       capsys)
    obj = json.loads(out)
    assert code == 1 and obj["status"] == "rejected" and obj["rejection"]["code"] == "no_calibration"
    assert "--lat/--lon" in obj["reason"] and obj["method"] == "mkc-em-attitude-stream"
    # with the position given, the same recording is calibrated
    code, out, _ = run(["calibrate", str(flight["no_position"]), "--stream", "--lat", str(LAT), "--lon", str(LON),
                        "--date", DATE, "--json", "-", "--quiet"], capsys)
    assert code == 0 and json.loads(out)["method"] == "mkc-em-attitude-stream"


def test_a_recording_without_attitude_is_refused_when_attitude_is_asked_for(flight, capsys):
    code, out, _ = run(["calibrate", str(flight["no_attitude"]), "--stream", "--attitude", "--json", "-", "--quiet"],
                       capsys)
    obj = json.loads(out)
    assert code == 1 and obj["rejection"]["code"] == "no_calibration" and "no attitude" in obj["reason"]


def test_an_attitude_without_a_position_falls_back_to_the_ellipsoid_stream_and_says_why(flight, capsys):
    code, out, _ = run(["calibrate", str(flight["no_position"]), "--stream", "--window", "128", "--json", "-"],
                       capsys)
    obj = json.loads(out)
    assert obj["method"] == "mkc-em-stream" and "attitude but no position" in obj["notes"][0]
