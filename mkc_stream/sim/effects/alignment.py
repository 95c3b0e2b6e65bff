"""The magnetometer's axes against the accelerometer/gyroscope axes.

* misalignment: the magnetometer frame is rotated by small angles (roll, pitch, yaw; 0.1-3 deg)
  from the IMU frame (assembly, PCB placement).
* cross_axis: the magnetometer's own axes are not orthogonal, B_meas = (I + K) B with K
  off-diagonal (0.1-2 deg per pair). The symmetric part of K is indistinguishable from soft iron;
  the antisymmetric part is a rotation against the IMU, i.e. the same observable as a
  misalignment. Both are visible only through the angle between the field and gravity, so they
  need an accelerometer.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .base import Effect, Param, SimContext


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


_deg = lambda n, t: Param(n, "deg", 0.1, 3.0, t)  # noqa: E731

MISALIGNMENT = Effect(
    name="misalignment", family="alignment", stage="field", kind="mean",
    params=(_deg("roll", 1.0), _deg("pitch", -0.7), _deg("yaw", 0.5)),
    needs=("acc",), forward=_misalignment_forward, testable=_needs_acc,
    doc="magnetometer frame rotated against the IMU frame")

CROSS_AXIS = Effect(
    name="cross_axis", family="alignment", stage="field", kind="mean",
    params=(_deg("xy", 0.8), _deg("xz", -0.4), _deg("yx", -0.3), _deg("yz", 0.6),
            _deg("zx", 0.2), _deg("zy", -0.5)),
    needs=("acc",), forward=_cross_axis_forward, testable=_needs_acc,
    doc="non-orthogonal magnetometer axes, (I + K)")

EFFECTS = (MISALIGNMENT, CROSS_AXIS)
