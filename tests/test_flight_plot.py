"""The report of the attitude-aided flight calibration as a PNG (flight/report_plot.py, `calibrate --plot`):
the file is a PNG of sane size, and what it draws is the fit's."""
from __future__ import annotations

import numpy as np
import pytest

from mkc_stream.cli import main
from mkc_stream.flight import fit_flight
from mkc_stream.flight.report_plot import DISTURBED_WEIGHT, instance_path, plot_flight_report, report_arrays
from mkc_stream.flight.simulated import simulated_flight

pytest.importorskip("matplotlib", reason="plots need pip install 'mkc-stream[plot]'")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
LAT, LON, ALT, DATE = 47.4, 8.5, 500.0, "2026-07-02"


@pytest.fixture(scope="module")
def disturbed_flight():
    """A 300 s level flight, 15% of its samples in disturbance bursts, and its fit."""
    f = simulated_flight(duration=300.0, rate=10.0, seed=4, disturbed=0.15, h_ned=(20.0, 1.0, 45.0))
    return f, fit_flight(f.recording, earth=f.truth["h_ned"])


def _assert_png(path):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert 20_000 < len(data) < 5_000_000                   # bytes: four panels of lines, not an empty canvas
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    assert 600 < img.shape[0] < 2000 and 900 < img.shape[1] < 3000
    assert float(np.std(img[..., :3])) > 0.05               # something is drawn


def test_the_report_is_a_png_and_draws_the_fit(disturbed_flight, tmp_path):
    f, fc = disturbed_flight
    path = tmp_path / "report.png"
    a = plot_flight_report(f.recording, fc, path, title="flight.csv")
    _assert_png(path)
    model = float(np.linalg.norm(f.truth["h_ned"]))
    assert a["field_model_uT"] == pytest.approx(model, rel=0.02)
    dev_before = np.median(np.abs(a["field_before_uT"] - a["field_model_uT"]))
    dev_after = np.median(np.abs(a["field_after_uT"] - a["field_model_uT"]))
    # the hard iron (12, -7, 20) uT puts the logged strength far off the model; calibrated it is on it
    assert dev_before > 5.0 and dev_after < 0.3
    # the weights drawn are the fit's, and the samples shaded as disturbed are the disturbed ones
    assert np.array_equal(a["weights"], fc.fit.weights)
    low = a["weight_min"] < DISTURBED_WEIGHT
    truth = f.truth["disturbed"]
    assert abs(a["disturbed_fraction"] - truth.mean()) < 0.05
    assert np.mean(truth[low]) > 0.8 and np.mean(low[truth]) > 0.8
    # the compensation line is the fitted current coefficient, and the scatter's slope on the clean samples agrees
    assert a["power_name"] == "current" and np.allclose(a["power_coeff"], fc.current / fc.scale)   # uT/A
    clean = ~truth
    X = np.stack([a["power"][clean], np.ones(clean.sum())], axis=1)
    slope = np.linalg.lstsq(X, a["partial_residual_uT"][clean], rcond=None)[0][0]
    assert np.allclose(slope, f.truth["K"], atol=0.01)
    # calibrated, the heading agrees with the attitude's (yaw error 3 deg RMS); the change from the raw is large
    assert np.median(np.abs(a["heading_vs_model_deg"][clean])) < 4.0
    assert np.median(np.abs(a["heading_change_deg"][clean])) > 10.0


def test_a_recording_the_calibration_was_not_fitted_on_is_refused(disturbed_flight):
    f, fc = disturbed_flight
    other = simulated_flight(duration=200.0, rate=10.0, seed=5)
    with pytest.raises(ValueError, match="not the recording"):
        report_arrays(other.recording, fc)


def _flight_csv(tmp_path, seed=2):
    from mkc_stream.flight.earthfield import earth_field
    from mkc_stream.io.recording import write_recording

    ef = earth_field(LAT, LON, ALT, DATE)
    f = simulated_flight(seed=seed, h_ned=tuple(ef.ned_uT), pitch_amp=0.25, bank_gain=25.0, duration=200.0, rate=10.0)
    rec = f.recording
    aux = dict(rec.aux)
    aux.update(lat=np.full(rec.t.shape, LAT), lon=np.full(rec.t.shape, LON), alt=np.full(rec.t.shape, ALT))
    path = tmp_path / "flight.csv"
    write_recording(path, rec.t, rec.mag, aux, {"units.mag": "uT", "date": DATE})
    return path


def test_calibrate_plot_writes_the_flight_report(tmp_path, capsys):
    pytest.importorskip("pygeomag")
    path = _flight_csv(tmp_path)
    png = tmp_path / "cal.png"
    code = main(["calibrate", str(path), "--plot", str(png), "--quiet"])
    assert code == 0
    _assert_png(png)


def test_calibrate_plot_to_an_unwritable_path_is_refused_before_the_work(tmp_path, capsys):
    path = tmp_path / "flight.csv"
    path.write_text("t,mx,my,mz\n")            # never read: the path is refused first
    code = main(["calibrate", str(path), "--plot", str(tmp_path / "no" / "cal.png"), "--quiet"])
    assert code == 2 and "does not exist" in capsys.readouterr().err


def test_all_instances_write_one_report_per_compass(tmp_path, monkeypatch, capsys):
    """--all-instances --plot PATH: PATH's name with -instance<id> for each compass (two compasses here)."""
    pytest.importorskip("pygeomag")
    from mkc_stream.ingest import flightlogs
    from mkc_stream.io.recording import read_recording

    csv = _flight_csv(tmp_path)
    log = tmp_path / "flight.bin"
    log.write_bytes(b"")
    monkeypatch.setattr(flightlogs, "is_flight_log", lambda p: True)
    monkeypatch.setattr(flightlogs, "inspect_flight_log", lambda p: {"instances": [{"id": 0}, {"id": 1}]})
    monkeypatch.setattr(flightlogs, "read_flight_log", lambda p: read_recording(csv))
    png = tmp_path / "cal.png"
    code = main(["calibrate", str(log), "--all-instances", "--plot", str(png)])
    out = capsys.readouterr().out
    assert code == 0
    for cid in (0, 1):
        want = tmp_path / f"cal-instance{cid}.png"
        assert instance_path(png, cid) == str(want)
        _assert_png(want)
        assert f"plot          : {want}" in out
    assert not png.exists()
