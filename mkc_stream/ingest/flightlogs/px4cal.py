"""The PX4 magnetometer calibration a log says was applied (``CAL_MAGn_*``), and its undoing.

Up to PX4 v1.11 the driver published m = (raw - off) * scale per axis (gauss), with the
``CAL_MAGn`` slot whose ``CAL_MAGn_ID`` is the sensor's device id; the sensors module then rotated
the board-level topics (``vehicle_magnetometer``, ``sensor_combined``) by the board rotation
R_b (``SENS_BOARD_ROT`` and the small ``SENS_BOARD_{X,Y,Z}_OFF`` trims, degrees). From v1.12
``sensor_mag`` is raw and the sensors module calibrates. Undone here:

* ``sensor_mag`` (<= v1.11): raw = m / scale + off;
* a board-level topic (<= v1.11, single slot in use, ``SENS_BOARD_ROT`` = 0):
  raw_body = R_b ((R_b^T m) / scale + off), R_b from the trims as Z-Y-X Euler angles;

anything else stays as logged, and the returned note says why.
"""
from __future__ import annotations

import numpy as np

from ._common import quat_from_euler

GAUSS_TO_UT = 100.0


def cal_slots(params) -> dict[int, dict]:
    slots = {}
    for n in range(4):
        p = f"CAL_MAG{n}_"
        if f"{p}ID" not in params:
            continue
        slots[n] = {"id": int(params[f"{p}ID"]), "enabled": bool(params.get(f"{p}EN", 1)),
                    "off": np.array([params.get(f"{p}{a}OFF", 0.0) for a in "XYZ"], dtype=np.float64),
                    "scale": np.array([params.get(f"{p}{a}SCALE", 1.0) for a in "XYZ"], dtype=np.float64)}
    return slots


def _rotation_of_quaternion(q) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def board_rotation(params) -> np.ndarray | None:
    """R_b of the board trims when SENS_BOARD_ROT is 0 (none), else None (not modelled here)."""
    if int(params.get("SENS_BOARD_ROT", 0)) != 0:
        return None
    ang = np.radians([float(params.get(f"SENS_BOARD_{a}_OFF", 0.0)) for a in "XYZ"])
    return _rotation_of_quaternion(quat_from_euler([ang[0]], [ang[1]], [ang[2]])[0])


def undo_px4(topic: str, version, dev, params, mag):
    """(mag G, note, applied-calibration dict or None) for one PX4 magnetometer stream."""
    new = version is not None and version >= (1, 12)
    if topic == "sensor_mag" and new:
        return mag, "raw: PX4 v1.12 and later publish sensor_mag before calibration", None
    if topic != "sensor_mag" and new:
        return mag, (f"calibrated, not undone: {topic} of PX4 v1.12+ is rotated and calibrated by the sensors "
                     "module, and the log does not say which sensor it used"), None
    slots = cal_slots(params)
    if dev is not None:
        chosen = [n for n, s in slots.items() if s["id"] == dev]
        why = f"the CAL_MAGn_ID equal to device_id {dev}"
    else:
        chosen = [n for n, s in slots.items() if s["id"] != 0 and s["enabled"]]
        why = "the only CAL_MAGn slot in use"
    if len(chosen) != 1:
        return mag, (f"calibrated by the driver, not undone: {len(chosen)} CAL_MAGn slots could be the one "
                     f"applied (the log does not say which)"), None
    n = chosen[0]
    s = slots[n]
    if not np.all(np.isfinite(s["scale"])) or np.any(s["scale"] == 0):
        return mag, f"calibrated by the driver, not undone: CAL_MAG{n} has a zero scale", None
    applied = {"slot": f"CAL_MAG{n}", "offset_uT": (s["off"] * GAUSS_TO_UT).tolist(), "scale": s["scale"].tolist()}
    if topic == "sensor_mag":
        raw = mag / s["scale"] + s["off"]                     # undo m = (raw - off) * scale
        applied["model"] = "m = (raw - off) * scale, per axis"
    else:
        R = board_rotation(params)
        if R is None:
            return mag, (f"calibrated by the driver, not undone: SENS_BOARD_ROT="
                         f"{params.get('SENS_BOARD_ROT')} is not modelled"), None
        raw = ((mag @ R) / s["scale"] + s["off"]) @ R.T       # rows: R_b ((R_b^T m) / scale + off)
        applied["model"] = "m = R_b ((raw - off) * scale), R_b the board trims"
    note = f"raw: the driver's CAL_MAG{n} offsets and scales were undone ({why})"
    if params.get("CAL_MAG_COMP_TYP", 0):
        note += f"; power compensation (CAL_MAG_COMP_TYP={params['CAL_MAG_COMP_TYP']}) not undone"
    return raw, note, applied
