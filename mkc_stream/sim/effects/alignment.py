"""The magnetometer's axes against the accelerometer/gyroscope axes.

* misalignment: the magnetometer frame is rotated by small angles (roll, pitch, yaw; 0.1-3 deg)
  from the IMU frame (assembly, PCB placement).
* cross_axis: the magnetometer's own axes are not orthogonal, B_meas = (I + K) B with K
  off-diagonal (0.1-2 deg per pair). The symmetric part of K is indistinguishable from soft iron;
  the antisymmetric part is a rotation against the IMU, i.e. the same observable as a
  misalignment. Both are visible only through the angle between the field and gravity, so they
  need an accelerometer.

Diagnosis: one form for both, a small rotation of the calibrated field against the
accelerometer (linear in its three angles). cross_axis is observed only through its
antisymmetric part, so its form is the misalignment's and the two are reported as ambiguous.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .base import Effect, Param, SimContext
from .form import MeanForm, single_design


def _misalignment_forward(ctx: SimContext, roll, pitch, yaw):
    R = Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix()
    ctx.B[:] = ctx.B @ R.T


def _cross_axis_forward(ctx: SimContext, xy, xz, yx, yz, zx, zy):
    K = np.radians(np.array([[0.0, xy, xz], [yx, 0.0, yz], [zx, zy, 0.0]]))
    ctx.B[:] = ctx.B @ (np.eye(3) + K).T


def _needs_acc(ev):
    if not ev.has_acc:
        return False, "needs an accelerometer (ax, ay, az): only the field-gravity angle reveals it"
    return True, "accelerometer present"


def _rotation_G(env, d):
    def g(frame, m, st):
        mc = (m - st.b) @ st.S.T
        Sinv = np.linalg.inv(st.S)
        out = np.zeros((m.shape[0], 3, 3))
        for k in range(3):
            ek = np.zeros(3)
            ek[k] = 1.0
            out[:, :, k] = np.cross(ek, mc) @ Sinv.T
        return out
    return g


def _rotation_magnitude(env, d, th):
    a = np.degrees(np.asarray(th))
    return {"value": float(np.linalg.norm(a)), "unit": "deg", "vector": a.tolist(),
            "meaning": "rotation of the magnetometer against the accelerometer"}


_deg = lambda n, t: Param(n, "deg", 0.1, 3.0, t)  # noqa: E731

MISALIGNMENT = Effect(
    name="misalignment", family="alignment", stage="field",
    params=(_deg("roll", 1.0), _deg("pitch", -0.7), _deg("yaw", 0.5)),
    needs=("acc",), forward=_misalignment_forward, testable=_needs_acc,
    form=MeanForm(single_design, _rotation_G, 3, _rotation_magnitude),
    doc="magnetometer frame rotated against the IMU frame")

CROSS_AXIS = Effect(
    name="cross_axis", family="alignment", stage="field",
    params=(_deg("xy", 0.8), _deg("xz", -0.4), _deg("yx", -0.3), _deg("yz", 0.6),
            _deg("zx", 0.2), _deg("zy", -0.5)),
    needs=("acc",), forward=_cross_axis_forward, testable=_needs_acc,
    form=MeanForm(single_design, _rotation_G, 3, _rotation_magnitude, alias_of="misalignment"),
    doc="non-orthogonal magnetometer axes, (I + K)")

EFFECTS = (MISALIGNMENT, CROSS_AXIS)
