"""A magnetometer's timing on recordings read at one sample a second (a long 50 Hz recording in
the fast profile). The dip rate (the panel's variable for a magnetometer sampled late against
the accelerometer) reads gravity from each sample's neighbours, never from the sample's own
accelerometer: the sample's dip residual holds that accelerometer's error, and a panel variable
sharing it gives the residual a trend per bin that no time-shifted dip replica has. The
gyroscope's timing test says "not testable" where the sensor turns too far between samples for
its central differences (a biased delay on null figure-8 recordings)."""
import dataclasses

import numpy as np
import pytest

from mkc_stream.diagnose.baseline import fit_baseline
from mkc_stream.diagnose.engine import Engine, neighbours_gravity
from mkc_stream.diagnose.frame import prepare
from mkc_stream.diagnose.gyro_timing import MAX_STEP_RAD, gyro_delay
from mkc_stream.sim import SensorModel, generate, simulate
from mkc_stream.sim.trajectory import moving_average


@pytest.fixture(scope="module")
def engine():
    """A figure-8 read at one sample a second (5 Hz decimated by 5), as a long 50 Hz recording
    is in the fast profile: the neighbours' accelerometer samples share no error with the
    sample's."""
    traj = generate("figure8", duration=1200, rate=5, seed=3)
    rec = simulate(traj, SensorModel(noise=0.1), seed=4).recording
    frame = prepare(rec, 1200)
    assert frame.decimation == 5 and frame.acc_unit is not None
    return Engine(frame, fit_baseline(frame), n_replicas=4)


def _swap(eng, acc_unit):
    """The same engine reading another accelerometer (only what _dip_rate reads changes)."""
    clone = object.__new__(Engine)
    clone.__dict__.update(eng.__dict__)
    clone.frame = dataclasses.replace(eng.frame, acc_unit=acc_unit)
    return clone


def test_dip_rate_does_not_follow_the_samples_own_accelerometer_error(engine):
    """An error on each sample's accelerometer along the field's motion (what a linear
    acceleration tied to the motion does), independent between samples: the dip rate moves with
    the neighbours' errors but not the sample's own, so its change is uncorrelated with it.
    With the sample's own gravity the correlation is 0.91."""
    frame = engine.frame
    g = frame.acc_unit
    v = moving_average(engine.base.fit.v, 5)
    vdot = np.gradient(v, frame.t, axis=0)
    along = vdot - np.sum(vdot * g, axis=1, keepdims=True) * g
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    eps = np.random.default_rng(0).normal(0.0, 0.1, frame.n)          # rad, per sample
    noisy = g + eps[:, None] * along
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    change = _swap(engine, noisy)._dip_rate() - engine._dip_rate()    # 1/s
    assert np.std(change) > 0.1 * np.std(engine._dip_rate())          # the error does reach it
    r = np.corrcoef(change, eps)[0, 1]
    assert abs(r) < 4.0 / np.sqrt(frame.n), r


def test_one_samples_accelerometer_moves_only_its_neighbours_dip_rate(engine):
    k = engine.frame.n // 2
    acc = engine.frame.acc_unit.copy()
    across = np.cross(acc[k], engine.base.fit.v[k])      # turns gravity towards the field's motion too
    acc[k] += 0.3 * across / np.linalg.norm(across)
    acc[k] /= np.linalg.norm(acc[k])
    moved = np.flatnonzero(~np.isclose(_swap(engine, acc)._dip_rate(), engine._dip_rate(), rtol=0, atol=1e-12))
    assert moved.tolist() == [k - 1, k + 1]


def test_a_missing_accelerometer_row_is_bridged_by_the_other_neighbour(engine):
    acc = engine.frame.acc_unit.copy()
    k = 100
    acc[k] = np.nan
    rate = _swap(engine, acc)._dip_rate()
    assert np.isfinite(rate).all()
    assert rate[k] == pytest.approx(engine._dip_rate()[k], abs=1e-12)      # reads k-1 and k+1 only


def test_neighbours_gravity_interpolates_in_time_and_handles_ends_and_gaps():
    z, y, x = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]
    g = np.array([z, z, y, x, x, z])
    t = np.array([0.0, 1.0, 2.0, 3.0, 7.0, 8.0])       # s; a 4 s hole between samples 3 and 4
    got = neighbours_gravity(g, t)
    np.testing.assert_allclose(got[0], z)              # one neighbour at each end
    np.testing.assert_allclose(got[5], x)
    np.testing.assert_allclose(got[1], np.array([0, 1, 1]) / np.sqrt(2))          # the midpoint of z and y
    w = (7.0 - 3.0) / (7.0 - 2.0)                       # sample 3 lies a fifth of the way from 2 to 4
    want = w * y + (1 - w) * x
    np.testing.assert_allclose(got[3], want / np.linalg.norm(want))
    g[2] = np.nan                                       # a missing row: its neighbours read the other side
    got = neighbours_gravity(g, t)
    np.testing.assert_allclose(got[1], z)
    np.testing.assert_allclose(got[3], x)
    both = neighbours_gravity(np.array([z, [np.nan] * 3, z, [np.nan] * 3, z]), np.arange(5.0))
    assert np.isnan(both[[0, 2, 4]]).all() and np.isfinite(both[[1, 3]]).all()     # no neighbour left
    with pytest.raises(ValueError, match="neighbours_gravity needs"):
        neighbours_gravity(g[:, :2], t)


def test_gyroscope_timing_is_not_testable_when_the_sensor_turns_far_between_samples(engine):
    frame, st = engine.frame, engine.base.fit.state
    far = gyro_delay(frame, st, engine.base.valid[:, 0])
    assert not far["testable"] and "rad between samples" in far["reason"] and "decimated by 5" in far["reason"]
    # the same figure-8 read at 20 Hz turns about 0.05 rad between samples: testable, no delay
    traj = generate("figure8", duration=300, rate=20, seed=3)
    near = prepare(simulate(traj, SensorModel(noise=0.1), seed=4).recording, 20000)
    assert np.median(np.linalg.norm(near.gyro, axis=1)) * near.dt0 < MAX_STEP_RAD
    got = gyro_delay(near, fit_baseline(near).fit.state)
    assert got["testable"] and abs(got["t"]) < 4.0, got
