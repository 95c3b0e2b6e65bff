"""The generated trajectory kinds: a ground vehicle turns about the vertical only, a static sensor
sees one direction, the older kinds draw what they drew before, and the diagnosis of a recording
that cannot determine an ellipsoid rejects the baseline and claims no effect."""
import numpy as np
import pytest

from mkc_stream.calib.acceptance import evaluate
from mkc_stream.commands.sim import TRAJECTORIES
from mkc_stream.diagnose import diagnose, report
from mkc_stream.diagnose.scope import CALIBRATION_FREE_EFFECTS
from mkc_stream.sim import SensorModel, generate, simulate
from mkc_stream.sim.trajectory import MOTIONS, _attitude

INCLINATION_DEG = 60.0       # generate's default: the field 60 deg below the horizontal


def _angle_deg(u, v):
    return np.degrees(np.arccos(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ground_tilts_a_few_degrees_and_visits_every_heading(seed):
    traj = generate("ground", duration=200.0, rate=50.0, seed=seed)
    u = traj.field_dir
    # every 10 deg heading bin of the horizontal field is visited over 200 s (full turns)
    az = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    counts, _ = np.histogram(az, bins=36, range=(-180.0, 180.0))
    assert np.all(counts > 0), np.flatnonzero(counts == 0)
    # level, the field is 90 - 60 = 30 deg from the sensor's -z axis; a tilt of a degrees moves it by <= a
    cone = _angle_deg(u, np.array([0.0, 0.0, -1.0]))
    assert np.all(np.abs(cone - (90.0 - INCLINATION_DEG)) < 10.0)
    # roll and pitch themselves: a few degrees RMS, never beyond 10 deg
    t = np.arange(10_000) / 50.0
    ypr = np.degrees(_attitude("ground", t, np.random.default_rng(seed)).as_euler("ZYX"))
    for tilt in (ypr[:, 1], ypr[:, 2]):
        assert 0.5 < np.sqrt(np.mean(tilt ** 2)) < 4.0
        assert np.max(np.abs(tilt)) < 10.0
    # the accelerometer's specific force stays near the sensor's +z (gravity, plus the vehicle's
    # own acceleration, which adds a few degrees in the turns)
    g = traj.acc / np.linalg.norm(traj.acc, axis=1, keepdims=True)
    assert np.median(_angle_deg(g, np.array([0.0, 0.0, 1.0]))) < 6.0


def test_static_sees_one_direction_in_a_random_attitude():
    dirs = []
    for seed in (0, 1, 2):
        u = generate("static", duration=200.0, rate=50.0, seed=seed).field_dir
        mean = u.mean(axis=0) / np.linalg.norm(u.mean(axis=0))
        assert np.max(_angle_deg(u, mean)) < 1.5            # 0.002 rad RMS per angle: ~0.5 deg at most
        assert np.max(_angle_deg(u, mean)) > 0.05           # but it does vibrate
        dirs.append(mean)
    # the attitude is drawn: three seeds, three directions
    assert min(_angle_deg(dirs[i], dirs[j]) for i, j in ((0, 1), (0, 2), (1, 2))) > 5.0


# generate(kind, duration=2, rate=50, seed=3), samples 0, 37, 99, computed before the ground and
# static kinds were added: the older kinds draw the same random numbers in the same order
BEFORE = {
    "hand": [[-0.7785032533358383, 0.5000000000000001, -0.37938461295302356],
             [-0.28152265502287344, 0.5737722975276269, -0.7691100995948114],
             [0.6483150744916716, 0.08036536550915875, -0.7571188626717985]],
    "figure8": [[0.0, -0.14902086989608238, -0.988834050958711],
                [0.9326031262543459, 0.27830998996055845, -0.22977153520132582],
                [-0.5508983178970727, -0.44789323342498855, -0.7042035890211611]],
    "flight": [[0.31415767189781457, -0.6782522092296804, -0.6642882641314709],
               [0.19143908039166724, -0.7357288702979237, -0.6496569155399899],
               [0.12618053382219624, -0.7301967689255601, -0.6714842898646385]],
}
# specific force (m/s^2) of the same hand trajectory, samples 0 and 99 (the linear acceleration's draws)
BEFORE_HAND_ACC = [[9.100873948691829, -0.04599218286991969, 4.8191925087190866],
                   [-1.45997426103509, -0.9303810818623606, 9.99369511163116]]


@pytest.mark.parametrize("kind", sorted(BEFORE))
def test_older_kinds_are_unchanged(kind):
    traj = generate(kind, duration=2, rate=50, seed=3)
    np.testing.assert_allclose(traj.field_dir[[0, 37, 99]], BEFORE[kind], rtol=0, atol=1e-12)
    if kind == "hand":
        np.testing.assert_allclose(traj.acc[[0, 99]], BEFORE_HAND_ACC, rtol=0, atol=1e-12)


def test_the_cli_offers_every_kind_and_an_unknown_one_is_named():
    assert tuple(TRAJECTORIES) == MOTIONS
    with pytest.raises(ValueError, match="ground, static"):
        generate("boat", duration=2, rate=50)


def _recording(kind, seed):
    traj = generate(kind, duration=40.0, rate=50.0, seed=seed)            # 2000 samples
    return simulate(traj, SensorModel(), seed=seed + 1).recording


def _claims_no_effect(d):
    scope = d.info["scope"]
    assert d.verdict == "baseline_rejected"
    assert not d.info["baseline"]["calibration"]["accepted"]
    assert d.selected == [] and scope["verdict_on_testable"] == "no_gap"
    # only what does not rest on the calibration was tested
    assert {r.name for r in d.effects if r.testable} <= set(CALIBRATION_FREE_EFFECTS)
    assert "sphere/norm" in scope["statistics_not_testable"]


def test_ground_diagnosis_rejects_the_baseline_for_coverage():
    """A yaw-only recording covers a circle of directions, not a sphere (a few seconds)."""
    d = diagnose(_recording("ground", 0), profile="fast", seed=0)
    _claims_no_effect(d)
    rejection = d.info["baseline"]["calibration"]["rejection"]
    assert "coverage" in rejection["failed"]
    assert "sphere coverage" in d.info["scope"]["calibration_reason"]
    # the report marks the rejected fit's field and noise as that fit's, not as measurements
    baseline_line = next(x for x in report.text(d).splitlines() if x.lstrip().startswith("baseline"))
    assert "(the rejected fit; not measurements)" in baseline_line


def test_static_diagnosis_rejects_the_baseline_and_claims_nothing():
    """One direction determines no ellipsoid; the calibrator names the failed fit (a few seconds)."""
    d = diagnose(_recording("static", 0), profile="fast", seed=0)
    _claims_no_effect(d)
    assert "the sensor barely turned" in d.info["scope"]["calibration_reason"]


def test_a_cloud_of_samples_is_named_as_such_only_when_its_field_is_below_the_range():
    """The fit-error reason tells a sensor that barely turned (a cloud: a large fit error about a
    field below the physical range) from a sphere with disturbances (the same error, a real field)."""
    quality = {"coverage": 1.0, "condition": 10.0, "outlier_fraction": 0.0}
    cloud = evaluate({**quality, "residual_rms": 0.42 * 0.3}, 0.3, "uT")
    assert "barely turned" in cloud.text and {"residual", "field_range"} <= set(cloud.failed)
    disturbed = evaluate({**quality, "residual_rms": 0.42 * 50.0}, 50.0, "uT")
    assert disturbed.failed == ("residual",) and "barely turned" not in disturbed.text
    unknown_unit = evaluate({**quality, "residual_rms": 0.42 * 0.3}, 0.3, "counts")
    assert "barely turned" not in unknown_unit.text
