"""ROS 2: a parameter YAML for the two common magnetometer consumers, in tesla.

* imu_filter_madgwick (imu_tools, http://wiki.ros.org/imu_filter_madgwick; ROS 2 node
  src/imu_filter_ros.cpp): ``mag_bias_x``, ``mag_bias_y``, ``mag_bias_z``, subtracted from the field
  (``mag_compensated = mag - mag_bias``). Hard iron only.
* magnetometer_pipeline's magnetometer_bias_remover (ctu-vras/compass,
  https://docs.ros.org/en/jazzy/p/magnetometer_pipeline/): ``initial_mag_bias_x/_y/_z`` and a
  row-major 3x3 scaling matrix, applied as ``scale * (field - bias)``
  (src/bias_remover.cpp, MagnetometerBiasRemover::removeBias). Its README names the matrix
  ``initial_scaling_matrix`` while the source reads ``initial_mag_scaling_matrix``: both are written,
  equal.

Both read sensor_msgs/MagneticField, whose field is in tesla
(https://docs.ros.org/en/api/sensor_msgs/html/msg/MagneticField.html). From this package's
calibration (u = tesla per unit; g = expected_field / F): bias = u b; scaling matrix = g S (exact).
The file is a ROS 2 parameter file for every node (``/**: ros__parameters:``).
"""
from __future__ import annotations

import pathlib
import re
from dataclasses import dataclass

import numpy as np

from .model import (CalibrationValues, ParamsFileError, as_list, fmt, max_direction_change_deg, parse_number,
                    raw_array, read_text)

TARGET = "ros"
RAW_UNIT = "T"
MADGWICK_KEYS = ("mag_bias_x", "mag_bias_y", "mag_bias_z")
REMOVER_KEYS = ("initial_mag_bias_x", "initial_mag_bias_y", "initial_mag_bias_z")
MATRIX_KEYS = ("initial_mag_scaling_matrix", "initial_scaling_matrix")
_KEY_LINE = re.compile(r"^(\s*)([A-Za-z_/*][A-Za-z0-9_/*]*)\s*:\s*(.*?)\s*$")


@dataclass(frozen=True)
class RosMagParams:
    madgwick_bias: np.ndarray   # mag_bias_x/y/z, T (imu_filter_madgwick)
    bias: np.ndarray            # initial_mag_bias_x/y/z, T (magnetometer_bias_remover)
    matrix: np.ndarray          # initial_mag_scaling_matrix, row-major 3x3


def convert(calibration) -> tuple[RosMagParams, list[str]]:
    cals = as_list(calibration)
    if len(cals) != 1:
        raise ValueError("a ROS parameter file holds one magnetometer's calibration: write one file per sensor")
    c = cals[0]
    u = c.tesla_per_unit
    M = c.gain * c.soft_iron
    note = [f"imu_filter_madgwick takes the hard iron only: its readings keep the soft iron, which "
            f"changes directions by up to {max_direction_change_deg(c.soft_iron):.3g} deg "
            "(magnetometer_bias_remover applies both)"]
    if c.current_coeff is not None or c.throttle_coeff is not None:
        coeffs = [f"{name} {np.linalg.norm(u * 1e6 * (c.soft_iron @ k)):.4g} uT per {per}"
                  for name, k, per in (("current", c.current_coeff, "A"), ("throttle", c.throttle_coeff, "full throttle"))
                  if k is not None]
        note.append("neither ROS node compensates current or throttle: left out (" + ", ".join(coeffs) + ")")
    if c.instance or c.device_id is not None:
        note.append("ROS parameters name no sensor: instance/device id are written as a comment only")
    return RosMagParams(u * c.hard_iron, u * c.hard_iron, M), note


def write(calibration, path) -> list[str]:
    p, note = convert(calibration)
    c = as_list(calibration)[0]
    row = ", ".join(fmt(v) for v in p.matrix.reshape(-1))
    lines = ["# Magnetometer calibration written by mkc_stream, ROS 2 parameters, tesla.",
             "# imu_filter_madgwick: field - mag_bias; magnetometer_bias_remover: matrix @ (field - bias)",
             f"# instance {c.instance}" + ("" if c.device_id is None else f", device id {c.device_id}"),
             "/**:", "  ros__parameters:"]
    lines += [f"    {k}: {fmt(v)}" for k, v in zip(MADGWICK_KEYS, p.madgwick_bias)]
    lines += [f"    {k}: {fmt(v)}" for k, v in zip(REMOVER_KEYS, p.bias)]
    lines += [f"    {k}: [{row}]" for k in MATRIX_KEYS]
    pathlib.Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return note


def read_values(path) -> dict:
    """key -> number or list of the flat ROS 2 parameter YAML this module writes (a strict subset of YAML:
    ``key: number`` and ``key: [numbers]``, nesting by indentation, ``#`` comments)."""
    path = pathlib.Path(path)
    text = read_text(path)
    values = {}
    for no, line in enumerate(text.splitlines(), 1):
        where = f"{path}:{no}"
        body = line.split("#", 1)[0].rstrip()
        if not body.strip():
            continue
        m = _KEY_LINE.match(body)
        if not m:
            raise ParamsFileError(f"{where}: expected 'key: value' (got {line.strip()!r})")
        key, value = m.group(2), m.group(3)
        if not value:
            continue                                   # a mapping: /**: or ros__parameters:
        if value.startswith("["):
            if not value.endswith("]"):
                raise ParamsFileError(f"{where}: {key}: a list must close on the same line")
            items = [s.strip() for s in value[1:-1].split(",")]
            parsed = [parse_number(s, where) for s in items if s]
        else:
            parsed = parse_number(value, where)
        if key in values:
            raise ParamsFileError(f"{where}: {key} is set twice")
        values[key] = parsed
    return values


def read(path) -> RosMagParams:
    values = read_values(path)
    missing = [k for k in MADGWICK_KEYS + REMOVER_KEYS if k not in values]
    if missing:
        raise ParamsFileError(f"{path}: missing {', '.join(missing)}")
    matrices = [values[k] for k in MATRIX_KEYS if k in values]
    if not matrices:
        raise ParamsFileError(f"{path}: missing the scaling matrix ({' or '.join(MATRIX_KEYS)})")
    for k in MATRIX_KEYS:
        if k in values and (not isinstance(values[k], list) or len(values[k]) != 9):
            raise ParamsFileError(f"{path}: {k} must be a list of 9 numbers (row-major 3x3)")
    if len(matrices) == 2 and matrices[0] != matrices[1]:
        raise ParamsFileError(f"{path}: {MATRIX_KEYS[0]} and {MATRIX_KEYS[1]} differ")
    for k in MADGWICK_KEYS + REMOVER_KEYS:
        if isinstance(values[k], list):
            raise ParamsFileError(f"{path}: {k} must be a number")
    return RosMagParams(np.array([values[k] for k in MADGWICK_KEYS]), np.array([values[k] for k in REMOVER_KEYS]),
                        np.array(matrices[0]).reshape(3, 3))


def apply(p: RosMagParams, raw, current=None, throttle=None, float32: bool = False) -> np.ndarray:
    """magnetometer_bias_remover on raw fields (N, 3) in tesla: matrix @ (field - bias). (ROS carries
    no power compensation: current/throttle are accepted and ignored; doubles throughout.)"""
    return (raw_array(raw) - p.bias) @ p.matrix.T


def apply_madgwick(p: RosMagParams, raw) -> np.ndarray:
    """imu_filter_madgwick's hard-iron correction: field - mag_bias, tesla."""
    return raw_array(raw) - p.madgwick_bias


def output_per_unit(c: CalibrationValues) -> float:
    return c.tesla_per_unit
