"""PX4: the CAL_MAGn_* calibration of each magnetometer as a QGroundControl ``.params`` file.

How PX4 corrects a reading (calibration::Magnetometer::Correct, src/lib/sensor_calibration/
Magnetometer.hpp, https://github.com/PX4/PX4-Autopilot/blob/main/src/lib/sensor_calibration/
Magnetometer.hpp), in gauss, in the SENSOR frame, before rotating to the body frame:

    m = R * (P * ((raw + power * COMP) - OFF))      # offsets are SUBTRACTED
    P = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]

(Magnetometer::set_offdiagonal puts XODIAG at (0,1)/(1,0), YODIAG at (0,2)/(2,0), ZODIAG at
(1,2)/(2,1)). ``power`` is the throttle (0..1) with CAL_MAG_COMP_TYP = 1, or the battery current
in kA (``current_a * 0.001f``, src/modules/sensors/vehicle_magnetometer/VehicleMagnetometer.cpp)
with CAL_MAG_COMP_TYP = 2 (battery 0) or 3 (battery 1). Parameter reference
(https://docs.px4.io/main/en/advanced_config/parameter_reference.html#CAL_MAG0_XOFF and
#CAL_MAG_COMP_TYP; the compensation procedure:
https://docs.px4.io/main/en/advanced_config/compass_power_compensation.html): CAL_MAGn_[XYZ]OFF
offsets, CAL_MAGn_[XYZ]SCALE scaling factors, CAL_MAGn_[XYZ]ODIAG off-diagonal factors,
CAL_MAGn_[XYZ]COMP "Unit for throttle-based compensation is [G] and for current-based compensation
[G/kA]", CAL_MAGn_ID the device id the slot belongs to (an INT32 holding the uint32 id).

From this package's calibration (u = gauss per unit; g = expected_field / F): OFF = u b;
P = g S (exact, symmetric); COMP = -1000 u k_I (G/kA) or -u k_T (G at full throttle).
The QGroundControl file (https://docs.qgroundcontrol.com/master/en/qgc-dev-guide/file_formats/
parameters.html): ``#`` comments, then one tab-separated ``vehicle-id component-id name value type``
per line, type a MAV_PARAM_TYPE (6 INT32, 9 REAL32).
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np

from .model import (CalibrationValues, ParamsFileError, as_list, check_instances, compensation_type,
                    float32_relative_step, fmt, parse_number, power_signal, raw_array, read_text)

TARGET = "px4"
RAW_UNIT = "G"
MAX_INSTANCES = 4
GAUSS_PER_TESLA = 1e4
COMP_TYPES = {0: "disabled", 1: "throttle", 2: "current (battery 0)", 3: "current (battery 1)"}
MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32 = 6, 9
INT_TYPES = {1, 2, 3, 4, 5, 6, 7, 8}     # MAV_PARAM_TYPE_UINT8 .. INT64
#: PX4's loader skips a scale closer than this (vector norm) to the one in use, and then also the
#: off-diagonals (Magnetometer::ParametersLoad: set_offset && set_scale && set_offdiagonal)
MIN_SCALE_CHANGE = 0.01


@dataclass(frozen=True)
class PX4Mag:
    """One CAL_MAGn slot as PX4 holds it (gauss; comp in G/kA or G at full throttle)."""
    instance: int
    offsets: np.ndarray      # CAL_MAGn_[XYZ]OFF, G, subtracted
    scales: np.ndarray       # CAL_MAGn_[XYZ]SCALE
    offdiagonals: np.ndarray  # CAL_MAGn_[XYZ]ODIAG
    comp: np.ndarray         # CAL_MAGn_[XYZ]COMP
    comp_type: int           # CAL_MAG_COMP_TYP (shared)
    device_id: int | None = None

    @property
    def matrix(self) -> np.ndarray:
        s, o = self.scales, self.offdiagonals
        return np.array([[s[0], o[0], o[1]], [o[0], s[1], o[2]], [o[1], o[2], s[2]]])


def param_names(instance: int) -> dict:
    n = f"CAL_MAG{instance}_"
    return {"OFF": [f"{n}{a}OFF" for a in "XYZ"], "SCALE": [f"{n}{a}SCALE" for a in "XYZ"],
            "ODIAG": [f"{n}{a}ODIAG" for a in "XYZ"], "COMP": [f"{n}{a}COMP" for a in "XYZ"],
            "ID": [f"{n}ID"]}


def convert(calibration) -> tuple[list[PX4Mag], list[str]]:
    cals = as_list(calibration)
    check_instances(cals, MAX_INSTANCES, "PX4")
    note = []
    comp_type = compensation_type(cals)
    out = []
    for c in cals:
        u = c.tesla_per_unit * GAUSS_PER_TESLA
        tag = f"CAL_MAG{c.instance}"
        P = c.gain * c.soft_iron
        comp = np.zeros(3)
        if comp_type == 2 and c.current_coeff is not None:
            comp = -1000.0 * u * c.current_coeff
        elif comp_type == 1 and c.throttle_coeff is not None:
            comp = -u * c.throttle_coeff
        if comp_type == 2 and c.throttle_coeff is not None:
            note.append(f"{tag}: CAL_MAG_COMP_TYP compensates current or throttle, not both: the throttle "
                        f"term is left out (up to {np.linalg.norm(u * c.throttle_coeff):.4g} G at full throttle)")
        strength = "the expected field" if c.expected_field is not None else \
            "F, the fitted strength (no expected_field given)"
        note.append(f"{tag}: soft iron exact (P = g S is symmetric, as PX4's scale matrix is); the field comes "
                    f"out at {c.gain * c.field * u:.6g} G, {strength}")
        if np.linalg.norm(np.diag(P) - 1.0) <= MIN_SCALE_CHANGE:
            note.append(f"{tag}: the scales are within {MIN_SCALE_CHANGE} of 1 (vector norm): PX4's loader "
                        "(src/lib/sensor_calibration/Magnetometer.cpp, set_scale) keeps the scale it holds "
                        "and skips the off-diagonals in that case; the soft iron may not be applied "
                        f"(it changes directions by up to {_max_angle(P):.3g} deg)")
        if c.device_id is None:
            note.append(f"{tag}: no device_id: CAL_MAG{c.instance}_ID is not written; PX4 applies the slot "
                        "only to the sensor whose id it holds")
        out.append(PX4Mag(c.instance, u * c.hard_iron, np.diag(P).copy(), np.array([P[0, 1], P[0, 2], P[1, 2]]),
                          comp, comp_type, c.device_id))
    if comp_type == 1:
        note.append("PX4 updates the throttle for compensation only while armed (VehicleMagnetometer.cpp)")
    note.append("PX4 corrects in the sensor frame, then rotates by CAL_MAGn_ROT / the board rotation: "
                "the calibration must come from unrotated sensor readings (no rotation is written)")
    note.append(f"the vehicle stores parameters as float32: each value is rounded to "
                f"{float32_relative_step():.1g} relative (the file itself is exact)")
    return out, note


def _max_angle(P):
    from .model import max_direction_change_deg
    return max_direction_change_deg(P / np.cbrt(np.linalg.det(P)))


def _signed32(device_id: int) -> int:
    """The uint32 device id as the INT32 parameter holds it."""
    return device_id - 2 ** 32 if device_id >= 2 ** 31 else device_id


def write(calibration, path, vehicle_id: int = 1, component_id: int = 1) -> list[str]:
    mags, note = convert(calibration)
    lines = [f"# Onboard parameters for Vehicle {vehicle_id} (magnetometer calibration written by mkc_stream)",
             "# field = P @ ((raw + power * COMP) - OFF), gauss; power = throttle or current in kA",
             "#",
             "# Vehicle-Id Component-Id Name Value Type"]

    def row(name, value, ptype):
        text = str(int(value)) if ptype == MAV_PARAM_TYPE_INT32 else fmt(value)
        lines.append(f"{vehicle_id}\t{component_id}\t{name}\t{text}\t{ptype}")

    for m in mags:
        names = param_names(m.instance)
        if m.device_id is not None:
            row(names["ID"][0], _signed32(m.device_id), MAV_PARAM_TYPE_INT32)
        for group, values in (("OFF", m.offsets), ("SCALE", m.scales), ("ODIAG", m.offdiagonals),
                              ("COMP", m.comp)):
            for n, v in zip(names[group], values):
                row(n, v, MAV_PARAM_TYPE_REAL32)
    row("CAL_MAG_COMP_TYP", mags[0].comp_type, MAV_PARAM_TYPE_INT32)
    pathlib.Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return note


def read_values(path) -> dict:
    """NAME -> value of a QGroundControl .params file; malformed rows raise ParamsFileError."""
    path = pathlib.Path(path)
    text = read_text(path)
    values = {}
    for no, line in enumerate(text.splitlines(), 1):
        where = f"{path}:{no}"
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.strip().split("\t")
        if len(fields) != 5:
            fields = line.split()
        if len(fields) != 5:
            raise ParamsFileError(f"{where}: expected 5 tab-separated fields "
                                  f"(vehicle-id component-id name value type), got {len(fields)}")
        vid, cid, name, value, ptype = (f.strip() for f in fields)
        for label, text_ in (("vehicle id", vid), ("component id", cid), ("type", ptype)):
            if not text_.isdigit():
                raise ParamsFileError(f"{where}: {label} {text_!r} is not a non-negative integer")
        ptype_i = int(ptype)
        if ptype_i not in INT_TYPES | {MAV_PARAM_TYPE_REAL32, 10}:
            raise ParamsFileError(f"{where}: type {ptype_i} is not a MAV_PARAM_TYPE (1..10)")
        v = parse_number(value, where)
        if ptype_i in INT_TYPES and v != int(v):
            raise ParamsFileError(f"{where}: {name} has integer type {ptype_i} but value {value!r}")
        if name in values:
            raise ParamsFileError(f"{where}: {name} is set twice")
        values[name] = v
    return values


def read(path) -> list[PX4Mag]:
    """The CAL_MAGn slots a .params file calibrates (offsets, scales and off-diagonals all given)."""
    values = read_values(path)
    comp_type = values.get("CAL_MAG_COMP_TYP", 0.0)
    if comp_type not in COMP_TYPES:
        raise ParamsFileError(f"{path}: CAL_MAG_COMP_TYP = {comp_type:g} is none of {sorted(COMP_TYPES)}")
    out = []
    for k in range(MAX_INSTANCES):
        names = param_names(k)
        needed = names["OFF"] + names["SCALE"] + names["ODIAG"]
        if not any(n in values for n in needed):
            continue
        missing = [n for n in needed if n not in values]
        if missing:
            raise ParamsFileError(f"{path}: CAL_MAG{k} is only partly given (missing {', '.join(missing)}): "
                                  "the vehicle would mix it with the values it holds")
        dev = values.get(names["ID"][0])
        out.append(PX4Mag(k, np.array([values[n] for n in names["OFF"]]),
                          np.array([values[n] for n in names["SCALE"]]),
                          np.array([values[n] for n in names["ODIAG"]]),
                          np.array([values.get(n, 0.0) for n in names["COMP"]]), int(comp_type),
                          None if dev is None else int(dev) % 2 ** 32))
    if not out:
        raise ParamsFileError(f"{path}: no magnetometer calibration (CAL_MAGn_*OFF/SCALE/ODIAG) in the file")
    return out


def apply(mag: PX4Mag, raw, current=None, throttle=None, float32: bool = False) -> np.ndarray:
    """PX4's Correct (without the final rotation) on raw sensor-frame readings (N, 3) in gauss;
    current in A (PX4 feeds it in kA), throttle 0..1. float32=True computes as the vehicle does."""
    dt = np.float32 if float32 else np.float64
    m = raw_array(raw).astype(dt)
    thr = power_signal(throttle, "throttle", len(m), mag.comp_type == 1)
    cur = power_signal(current, "current", len(m), mag.comp_type in (2, 3))
    if thr is not None:
        m = m + thr.astype(dt)[:, None] * mag.comp.astype(dt)[None, :]
    elif cur is not None:
        m = m + (cur * 0.001).astype(dt)[:, None] * mag.comp.astype(dt)[None, :]
    m = (m - mag.offsets.astype(dt)) @ mag.matrix.astype(dt).T
    return m.astype(float)


def output_per_unit(c: CalibrationValues) -> float:
    return c.tesla_per_unit * GAUSS_PER_TESLA
