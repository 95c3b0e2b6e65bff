"""FlightStreamCalibrator as a calibrator: trial, pool, accepted Calibration, status and gates
(mkc_stream/flight/streaming.py)."""
from __future__ import annotations

import numpy as np
import pytest

from mkc_stream.calib.result import Calibration
from mkc_stream.calib.streaming import NotCalibratedError
from mkc_stream.flight.simulated import simulated_flight
from mkc_stream.flight.streaming import FlightStreamCalibrator

QUAT = ("qw", "qx", "qy", "qz")


def _inputs(duration, seed=1, disturbed=0.0):
    sf = simulated_flight(duration=duration, rate=25, seed=seed, disturbed=disturbed, yaw_error_deg=0.0)
    rec = sf.recording
    return sf.truth, rec.mag, np.stack([rec.aux[c] for c in QUAT], 1), rec.aux["current"][:, None]


def test_the_accepted_calibration_is_a_calibration_with_compensation():
    tr, mag, q, c = _inputs(200.0)
    cal = FlightStreamCalibrator(tr["h_ned"], ("current",), window=256, delay_samples=1, sample_rate=25.0)
    with pytest.raises(NotCalibratedError):
        cal.apply(mag[:1], c[:1])
    events = cal.learn_many(mag[:100], q[:100], c[:100])
    assert all(not ev.accepted and ev.reason.startswith("warming up") for ev in events)
    assert cal.status().code == "warming_up" and cal.accepted is None
    events += cal.learn_one(mag[100], q[100], c[100])
    for s in range(101, mag.shape[0], 500):
        events += cal.learn_many(mag[s:s + 500], q[s:s + 500], c[s:s + 500])
    assert events == cal.history and any(ev.accepted for ev in events)
    acc = cal.accepted
    assert isinstance(acc, Calibration) and acc.accepted and cal.status() is None
    assert acc.method == "mkc-em-attitude-stream" and acc.pooled > 1
    assert np.linalg.norm(acc.hard_iron - tr["b"]) < 0.6
    assert np.abs(acc.current - tr["K"]).max() < 0.03 and acc.delay_s == pytest.approx(0.04)
    assert len(acc.uncertainty["hard_iron_sd"]) == 3 and all(s > 0 for s in acc.uncertainty["hard_iron_sd"])
    ci = acc.power_ci["current"]
    assert np.all((ci[:, 0] <= acc.current) & (acc.current <= ci[:, 1]))
    # the compensated, calibrated field has the fitted strength (noise 0.1 uT, attitude-free check)
    n = np.linalg.norm(cal.apply(mag[-500:], c[-500:]), axis=1)
    assert abs(np.median(n) - acc.field) < 0.3
    obj = acc.to_json(counts=cal.counts())
    assert obj["compensation"]["current_unit"] == "uT/A" and obj["earth_field"] is None
    assert obj["status"] == "accepted" and obj["attitude_fit"]["held"] == ["A02=A20", "A12=A21"]


def test_pooling_the_windows_beats_the_last_window_when_a_quarter_is_disturbed():
    tr, mag, q, c = _inputs(600.0, seed=3, disturbed=0.25)
    cal = FlightStreamCalibrator(tr["h_ned"], ("current",), window=512, delay_samples=1)
    for s in range(0, mag.shape[0], 1000):
        cal.learn_many(mag[s:s + 1000], q[s:s + 1000], c[s:s + 1000])
    pooled = np.linalg.norm(cal.accepted.hard_iron - tr["b"])
    window = np.linalg.norm(cal.calibration(pooled=False)["hard_iron"] - tr["b"])
    assert pooled < 0.5 < window                       # measured 0.32 and 1.27 uT


def test_a_field_far_from_the_model_is_never_accepted():
    tr, mag, q, c = _inputs(120.0)
    cal = FlightStreamCalibrator(tr["h_ned"], ("current",), window=256)
    cal.learn_many(2.0 * mag, q, c)                     # a sensor in uT reading twice the model's field
    st = cal.status()
    assert cal.accepted is None and st.code == "rejected" and "field_model" in st.failed
    assert st.values["scale"] == pytest.approx(2.0, rel=0.05)
    # counts: no unit check, the same data are accepted
    cal = FlightStreamCalibrator(tr["h_ned"], ("current",), window=256, unit="counts")
    cal.learn_many(2.0 * mag, q, c)
    assert cal.accepted is not None and cal.accepted.scale == pytest.approx(2.0, rel=0.05)


def test_it_speaks_the_verbs_of_mag_calibrator():
    from mkc_stream.calib.streaming import MagCalibrator

    shared = ("learn_one", "learn_many", "accepted", "trial", "status", "status_reason", "history", "apply", "counts",
              "first_accepted_at", "last_event", "reset", "nbytes")
    flight, ellipsoid = FlightStreamCalibrator([20.0, 1.0, 45.0]), MagCalibrator()
    assert [n for n in shared if not hasattr(flight, n)] == [] and [n for n in shared if not hasattr(ellipsoid, n)] == []
    assert flight.status().code == ellipsoid.status().code == "warming_up"


def test_the_yaw_error_term_keeps_a_wandering_yaw_out_of_the_hard_iron():
    sf = simulated_flight(duration=600, rate=25, seed=1, disturbed=0.1, yaw_error_deg=3.0)
    rec, tr = sf.recording, sf.truth
    q, c = np.stack([rec.aux[n] for n in QUAT], 1), rec.aux["current"][:, None]
    err = {}
    for prior in (None, 5.0):
        cal = FlightStreamCalibrator(tr["h_ned"], ("current",), window=512, delay_samples=1, yaw_prior_deg=prior)
        for s in range(0, rec.mag.shape[0], 1000):
            cal.learn_many(rec.mag[s:s + 1000], q[s:s + 1000], c[s:s + 1000])
        err[prior] = np.linalg.norm(cal.accepted.hard_iron - tr["b"])
    assert err[5.0] < 0.4 < 1.0 < err[None]                 # measured 0.26 and 2.00 uT
    with pytest.raises(Exception, match="yaw_prior_deg"):
        FlightStreamCalibrator(tr["h_ned"], yaw_prior_deg=0.0)
