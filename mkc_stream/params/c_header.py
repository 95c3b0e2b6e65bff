"""A C header with the calibration as ``static const`` arrays, for firmware built on firmware_ref.

The arrays have the layout of firmware_ref's ``mkc_mag_calibration`` (include/mkc.h: ``hard_iron[3]``,
``soft_iron[3][3]`` with m_cal = S (m_raw - b), ``field``), in the calibration's own unit, so the
header carries this package's calibration exactly (doubles, written to round-trip):

    m_out = GAIN * S (m_raw - b - CURRENT_COEFF * current - THROTTLE_COEFF * throttle)

The element type is ``MKC_CAL_REAL``: ``mkc_real`` when mkc.h was included first, else ``double``;
define it before including to choose. Each compass's names carry its instance
(``MKC_MAG0_HARD_IRON``, ...). No functions: the header compiles with
``cc -std=c99 -Wall -Wextra -Werror -pedantic``.
"""
from __future__ import annotations

import pathlib
import re
from dataclasses import dataclass

import numpy as np

from .model import CalibrationValues, ParamsFileError, as_list, fmt, power_signal, raw_array, read_text

TARGET = "c"
GUARD = "MKC_MAG_CALIBRATION_H"
_ARRAY = re.compile(r"static\s+const\s+MKC_CAL_REAL\s+(?:MKC_CAL_UNUSED\s+)?(MKC_MAG(\d+)_([A-Z_]+))\s*((?:\[\d+\])*)\s*=\s*"
                    r"(\{[^;]*\}|[^;{}]+)\s*;")
_INT = re.compile(r"static\s+const\s+(?:long|unsigned long|int)\s+(?:MKC_CAL_UNUSED\s+)?(MKC_MAG(\d+)_([A-Z_]+))\s*=\s*([0-9]+)[uUlL]*\s*;")
_UNIT = re.compile(r"#define\s+MKC_MAG(\d+)_UNIT\s+\"([^\"]*)\"")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass(frozen=True)
class HeaderCalibration:
    instance: int
    unit: str
    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field: float
    gain: float
    current_coeff: np.ndarray
    throttle_coeff: np.ndarray
    device_id: int | None = None


def _c_list(values) -> str:
    return "{" + ", ".join(fmt(v) for v in values) + "}"


def write(calibration, path) -> list[str]:
    cals = as_list(calibration)
    lines = ["/* Magnetometer calibration written by mkc_stream, for firmware using firmware_ref.",
             " * m_out = GAIN * S (m_raw - b - CURRENT_COEFF * current_A - THROTTLE_COEFF * throttle),",
             " * throttle in 0..1; S symmetric positive definite with det 1; |m_out| = GAIN * FIELD. */",
             f"#ifndef {GUARD}", f"#define {GUARD}", "",
             "#ifndef MKC_CAL_REAL", "#ifdef MKC_H", "#define MKC_CAL_REAL mkc_real", "#else",
             "#define MKC_CAL_REAL double", "#endif", "#endif",
             "/* a program uses some arrays: GCC need not warn about the others (clang never does in a header) */",
             "#if defined(__GNUC__) && !defined(__clang__)",
             "#define MKC_CAL_UNUSED __attribute__((unused))", "#else", "#define MKC_CAL_UNUSED", "#endif"]
    for c in cals:
        p = f"MKC_MAG{c.instance}_"
        u = c.unit.strip().replace("\u00b5", "u").replace("\u03bc", "u")   # ASCII for the C source
        kI = np.zeros(3) if c.current_coeff is None else c.current_coeff
        kT = np.zeros(3) if c.throttle_coeff is None else c.throttle_coeff
        S = c.soft_iron
        lines += ["", f"/* compass instance {c.instance} */",
                  f"#define {p}UNIT \"{u}\"",
                  f"static const MKC_CAL_REAL MKC_CAL_UNUSED {p}HARD_IRON[3] = {_c_list(c.hard_iron)};  /* b, {u} */",
                  f"static const MKC_CAL_REAL MKC_CAL_UNUSED {p}SOFT_IRON[3][3] = {{{_c_list(S[0])}, {_c_list(S[1])}, "
                  f"{_c_list(S[2])}}};  /* S, dimensionless */",
                  f"static const MKC_CAL_REAL MKC_CAL_UNUSED {p}FIELD = {fmt(c.field)};  /* F, {u} */",
                  f"static const MKC_CAL_REAL MKC_CAL_UNUSED {p}GAIN = {fmt(c.gain)};  /* expected field / F (1: none given) */",
                  f"static const MKC_CAL_REAL MKC_CAL_UNUSED {p}CURRENT_COEFF[3] = {_c_list(kI)};  /* k_I, {u}/A */",
                  f"static const MKC_CAL_REAL MKC_CAL_UNUSED {p}THROTTLE_COEFF[3] = {_c_list(kT)};  /* k_T, {u} at full throttle */"]
        if c.device_id is not None:
            lines.append(f"static const unsigned long MKC_CAL_UNUSED {p}DEVICE_ID = {c.device_id}UL;")
    lines += ["", f"#endif /* {GUARD} */"]
    pathlib.Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return ["the header is exact (float64 literals); with MKC_USE_FLOAT the firmware rounds them to float32"]


def read(path) -> list[HeaderCalibration]:
    path = pathlib.Path(path)
    text = read_text(path)
    found: dict = {}
    for m in _ARRAY.finditer(text):
        k, what, dims, body = int(m.group(2)), m.group(3), m.group(4), m.group(5)
        numbers = [float(x) for x in _NUMBER.findall(body)]
        shape = tuple(int(d) for d in re.findall(r"\[(\d+)\]", dims))
        size = int(np.prod(shape)) if shape else 1
        if len(numbers) != size:
            raise ParamsFileError(f"{path}: {m.group(1)} has {len(numbers)} values, its shape {shape} needs {size}")
        found.setdefault(k, {})[what] = np.array(numbers).reshape(shape) if shape else numbers[0]
    for m in _INT.finditer(text):
        found.setdefault(int(m.group(2)), {})[m.group(3)] = int(m.group(4))
    units = {int(m.group(1)): m.group(2) for m in _UNIT.finditer(text)}
    out = []
    for k in sorted(found):
        v = found[k]
        missing = [n for n in ("HARD_IRON", "SOFT_IRON", "FIELD", "GAIN", "CURRENT_COEFF", "THROTTLE_COEFF")
                   if n not in v]
        if missing or k not in units:
            raise ParamsFileError(f"{path}: compass {k} lacks {', '.join(missing + ([] if k in units else ['UNIT']))}")
        if np.shape(v["HARD_IRON"]) != (3,) or np.shape(v["SOFT_IRON"]) != (3, 3):
            raise ParamsFileError(f"{path}: compass {k}: HARD_IRON must be [3] and SOFT_IRON [3][3]")
        out.append(HeaderCalibration(k, units[k], v["HARD_IRON"], v["SOFT_IRON"], float(v["FIELD"]),
                                     float(v["GAIN"]), v["CURRENT_COEFF"], v["THROTTLE_COEFF"], v.get("DEVICE_ID")))
    if not out:
        raise ParamsFileError(f"{path}: no MKC_MAGn_* calibration arrays in the header")
    return out


def apply(h: HeaderCalibration, raw, current=None, throttle=None, float32: bool = False) -> np.ndarray:
    """What firmware does with the header: GAIN * S (m_raw - b - k_I current - k_T throttle), in the unit."""
    dt = np.float32 if float32 else np.float64
    m = raw_array(raw).astype(dt) - h.hard_iron.astype(dt)
    cur = power_signal(current, "current", len(m), bool(np.any(h.current_coeff)))
    thr = power_signal(throttle, "throttle", len(m), bool(np.any(h.throttle_coeff)))
    if cur is not None:
        m = m - cur.astype(dt)[:, None] * h.current_coeff.astype(dt)[None, :]
    if thr is not None:
        m = m - thr.astype(dt)[:, None] * h.throttle_coeff.astype(dt)[None, :]
    return (dt(h.gain) * (m @ h.soft_iron.astype(dt).T)).astype(float)


def output_per_unit(c: CalibrationValues) -> float:
    return 1.0
