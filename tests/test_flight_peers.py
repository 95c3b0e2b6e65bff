"""The flight study's MagFit peer (tools/peer_magfit.py): its closed-form cost is MagFit's construction, its
gradient is the cost's, and on a noiseless simulated flight it recovers the truth."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from mkc_stream.flight.simulated import simulated_flight
from mkc_stream.flight.vector_fit import rotation_matrices

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import peer_magfit as PM  # noqa: E402  (tools/peer_magfit.py)

pytest.importorskip("scipy")

H_NED = np.array([21.0, 1.5, 42.0])          # uT
SOFT = np.array([[1.03, 0.02, -0.01], [0.02, 0.97, 0.015], [-0.01, 0.015, 1.0]])


def _flight(**kw):
    S = SOFT / np.linalg.det(SOFT) ** (1.0 / 3.0)
    args = dict(duration=240.0, rate=10.0, seed=5, h_ned=tuple(H_NED), noise=0.0, yaw_error_deg=0.0,
                tilt_error_deg=0.0, delay=0.0, soft_iron=S, hard_iron=(14.0, -9.0, 22.0), k_current=(0.12, -0.06, 0.2))
    args.update(kw)
    f = simulated_flight(**args)
    rec = f.recording
    R = rotation_matrices(np.stack([rec.aux[c] for c in ("qw", "qx", "qy", "qz")], axis=1))
    return rec, R, f.truth


def _euler(R):
    """(roll, pitch) of body -> NED matrices R = Rz Ry Rx."""
    return np.arctan2(R[:, 2, 1], R[:, 2, 2]), -np.arcsin(np.clip(R[:, 2, 0], -1, 1))


def _rzyx(yaw, pitch, roll):
    """Rz(yaw) Ry(pitch) Rx(roll), body -> NED."""
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    Ry = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    Rx = np.array([[1, 0, 0], [0, math.cos(roll), -math.sin(roll)], [0, math.sin(roll), math.cos(roll)]])
    return Rz @ Ry @ Rx


def test_the_closed_form_cost_is_magfits_heading_from_the_sample_construction():
    """MagFit's error per sample: the corrected sample c against R(roll, pitch, yaw_c)^T h_E, yaw_c the
    tilt-compensated heading of c itself plus the declination; the peer's closed form must equal it."""
    rec, R, _ = _flight(duration=60.0)
    rng = np.random.default_rng(1)
    p = np.concatenate([rng.uniform(-20, 20, 3), [1.0], rng.uniform(0.9, 1.1, 3), rng.uniform(-0.05, 0.05, 3),
                        rng.uniform(-0.3, 0.3, 3)])
    cur = rec.aux["current"]
    fast, _ = PM._cost_and_gradient(p, rec.mag, R, cur, math.hypot(H_NED[0], H_NED[1]), H_NED[2])
    o, s, M, cmot = PM._unpack(p)
    roll, pitch = _euler(R)
    decl = math.atan2(H_NED[1], H_NED[0])
    errs = []
    for k in range(rec.t.shape[0]):
        c = M @ (s * (rec.mag[k] + o)) + cmot * cur[k]
        level = _rzyx(0.0, pitch[k], roll[k]) @ c              # the tilt-compensated field
        yaw = math.atan2(-level[1], level[0]) + decl         # heading of the sample (MagFit: atan2(-headY, headX))
        expected = _rzyx(yaw, pitch[k], roll[k]).T @ H_NED
        errs.append(np.linalg.norm(expected - c))
    assert fast == pytest.approx(float(np.mean(errs)), rel=1e-9, abs=1e-9)
    assert fast > 1.0                                   # the parameters are wrong: the comparison is not 0 = 0


def test_the_gradient_is_the_costs():
    rec, R, _ = _flight(duration=60.0, noise=0.3)
    rng = np.random.default_rng(2)
    p = np.concatenate([rng.uniform(-20, 20, 3), [1.05], rng.uniform(0.9, 1.1, 3), rng.uniform(-0.05, 0.05, 3),
                        rng.uniform(-0.3, 0.3, 3)])
    args = (rec.mag, R, rec.aux["current"], math.hypot(H_NED[0], H_NED[1]), H_NED[2])
    _, g = PM._cost_and_gradient(p, *args)
    num = np.empty(13)
    for j in range(13):
        e = np.zeros(13)
        e[j] = 1e-6
        num[j] = (PM._cost_and_gradient(p + e, *args)[0] - PM._cost_and_gradient(p - e, *args)[0]) / 2e-6
    assert np.allclose(g, num, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("level", [True, False], ids=["level-flight", "pitched-flight"])
def test_magfit_recovers_the_truth_of_a_noiseless_flight(level):
    kw = {} if level else dict(pitch_amp=0.25, bank_gain=25.0)
    rec, R, truth = _flight(**kw)
    r = PM.magfit(rec.mag, R, H_NED, rec.aux["current"])
    A, b, K = r.vector_model()
    assert r.success and r.cost < 1e-6
    assert np.allclose(b, truth["b"], atol=1e-5)
    assert np.allclose(A, truth["A"], atol=1e-7)
    assert np.allclose(K, truth["K"], atol=1e-7)


def test_magfit_stops_at_its_bounds():
    """A hard iron beyond MagFit's +-1500 mGauss (150 uT) offset bound is not reached: the offset sits on the bound."""
    rec, R, truth = _flight(hard_iron=(170.0, -9.0, 22.0))
    r = PM.magfit(rec.mag, R, H_NED, rec.aux["current"])
    assert r.offsets[0] == pytest.approx(-PM.OFFSET_MAX_UT, abs=1e-6)
    assert np.all(np.abs(r.offsets) <= PM.OFFSET_MAX_UT + 1e-9)
    assert np.all((np.diag(r.M) >= PM.DIAGONAL[0] - 1e-9) & (np.diag(r.M) <= PM.DIAGONAL[1] + 1e-9))
