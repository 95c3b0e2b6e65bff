"""ArduPilot: the COMPASS_* calibration of each compass as a ``.param`` file (Mission Planner, MAVProxy).

How ArduPilot corrects a reading (AP_Compass_Backend::correct_field, libraries/AP_Compass/
AP_Compass_Backend.cpp, https://github.com/ArduPilot/ardupilot/blob/master/libraries/AP_Compass/
AP_Compass_Backend.cpp), after rotating the raw field into the body frame (rotate_field:
COMPASS_ORIENTn for an external compass, AHRS_ORIENTATION for an internal one), all in milligauss:

    m = raw + OFS                                   # offsets are ADDED
    m = SCALE * m        only if 1/1.5 <= SCALE <= 1.5 (Compass::have_scale_factor; 0 = no scaling)
    m = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]] @ m
    m = m + MOT * throttle   (COMPASS_MOTCT = 1, throttle 0..1)
      or m + MOT * current   (COMPASS_MOTCT = 2, current in A)  # after the matrix, in the output frame

Units and names from the parameter documentation (https://ardupilot.org/copter/docs/parameters.html
#compass-parameters, generated from the @Param blocks of libraries/AP_Compass/AP_Compass.cpp):
COMPASS_OFS_X "Offset to be added to the compass x-axis values", mGauss, range -400..400;
COMPASS_DIA_X / COMPASS_ODI_X "in the compass soft-iron calibration matrix: [[DIA_X, ODI_X, ODI_Y],
[ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]"; COMPASS_SCALE "If this is 0 then no scaling is done";
COMPASS_MOT_X "Multiplied by the current throttle and added to the compass's x-axis values",
mGauss/A (or mGauss at full throttle), range -1000..1000; COMPASS_MOTCT 0 disabled, 1 throttle,
2 current (one setting for every compass). The second and third compass: COMPASS_OFS2_X,
COMPASS_DIA2_X, COMPASS_ODI2_X, COMPASS_MOT2_X, COMPASS_SCALE2 (and 3). COMPASS_DEV_ID is read-only
on the vehicle, so it is written as a comment only.

From this package's calibration (1 uT = 10 mGauss; u = mGauss per unit; g = expected_field / F):
OFS = -u b; DIA/ODI = S (symmetric: exact); SCALE = g (0 without an expected field; a g outside
ArduPilot's accepted range is folded into DIA/ODI instead); MOT = -g u S k_I (per A) or
-g u S k_T (at full throttle). The file format: one ``NAME,VALUE`` per line, ``#`` comments
(Mission Planner's save format; MAVProxy's ``param load`` reads commas as separators too).
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np

from .model import (CalibrationValues, ParamsFileError, as_list, check_instances, compensation_type,
                    float32_relative_step, fmt, parse_number, power_signal, raw_array, read_text)

TARGET = "ardupilot"
#: the unit of the raw readings ArduPilot corrects and of its output
RAW_UNIT = "mG"
MAX_INSTANCES = 3
#: Compass::have_scale_factor applies COMPASS_SCALE only inside [1/1.5, 1.5] (COMPASS_MAX_SCALE_FACTOR)
SCALE_RANGE = (1.0 / 1.5, 1.5)
#: documented ranges (@Range) of the offsets and motor coefficients, mGauss and mGauss/A
OFS_RANGE = 400.0
MOT_RANGE = 1000.0
MOTCT_NAMES = {0: "disabled", 1: "throttle", 2: "current"}
MG_PER_TESLA = 1e7


@dataclass(frozen=True)
class ArduPilotCompass:
    """One compass's parameters as ArduPilot holds them (mGauss; motor_comp per A or at full throttle)."""
    instance: int
    offsets: np.ndarray       # COMPASS_OFSn_X/Y/Z, mGauss, added to the raw field
    diagonals: np.ndarray     # COMPASS_DIAn_X/Y/Z
    offdiagonals: np.ndarray  # COMPASS_ODIn_X/Y/Z
    scale: float              # COMPASS_SCALEn (0: not applied)
    motor_comp: np.ndarray    # COMPASS_MOTn_X/Y/Z
    motct: int                # COMPASS_MOTCT (shared by every compass)
    device_id: int | None = None

    @property
    def matrix(self) -> np.ndarray:
        d, o = self.diagonals, self.offdiagonals
        return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


def param_names(instance: int) -> dict:
    """The parameter names of compass `instance` (0-based): group -> names."""
    k = "" if instance == 0 else str(instance + 1)
    return {"OFS": [f"COMPASS_OFS{k}_{a}" for a in "XYZ"],
            "DIA": [f"COMPASS_DIA{k}_{a}" for a in "XYZ"],
            "ODI": [f"COMPASS_ODI{k}_{a}" for a in "XYZ"],
            "MOT": [f"COMPASS_MOT{k}_{a}" for a in "XYZ"],
            "SCALE": [f"COMPASS_SCALE{k}"],
            "DEV_ID": [f"COMPASS_DEV_ID{k}"]}


def convert(calibration) -> tuple[list[ArduPilotCompass], list[str]]:
    """ArduPilot's parameters for each calibration, and the note of what is not exact."""
    cals = as_list(calibration)
    check_instances(cals, MAX_INSTANCES, "ArduPilot")
    note = []
    motct = compensation_type(cals)
    out = []
    for c in cals:
        u = c.tesla_per_unit * MG_PER_TESLA
        g = c.gain
        tag = f"compass {c.instance + 1}"
        M = c.soft_iron.copy()
        scale = 0.0
        if c.expected_field is not None:
            if SCALE_RANGE[0] <= g <= SCALE_RANGE[1]:
                scale = g
            else:
                M = g * M
                note.append(f"{tag}: expected_field/F = {g:.6g} is outside the range ArduPilot applies "
                            f"COMPASS_SCALE in ({SCALE_RANGE[0]:.4g}..{SCALE_RANGE[1]:.4g}): folded into "
                            "DIA/ODI instead (exact, but the matrix no longer has det 1)")
        mot = np.zeros(3)
        if motct == 2 and c.current_coeff is not None:
            mot = -g * u * (c.soft_iron @ c.current_coeff)
        elif motct == 1 and c.throttle_coeff is not None:
            mot = -g * u * (c.soft_iron @ c.throttle_coeff)
        if motct == 2 and c.throttle_coeff is not None:
            size = np.linalg.norm(g * u * (c.soft_iron @ c.throttle_coeff))
            note.append(f"{tag}: COMPASS_MOTCT can compensate current or throttle, not both: the throttle "
                        f"term is left out (up to {size:.4g} mGauss at full throttle)")
        ofs = -u * c.hard_iron
        if np.any(np.abs(ofs) > OFS_RANGE):
            note.append(f"{tag}: offsets {np.round(ofs, 1).tolist()} mGauss exceed the documented range "
                        f"+-{OFS_RANGE:g}; the arming check compares them with COMPASS_OFFS_MAX")
        if np.any(np.abs(mot) > MOT_RANGE):
            note.append(f"{tag}: motor compensation {np.round(mot, 1).tolist()} exceeds the documented "
                        f"range +-{MOT_RANGE:g}")
        strength = "the expected field" if c.expected_field is not None else \
            "F, the fitted strength (no expected_field given)"
        note.append(f"{tag}: soft iron exact (S is symmetric, as the DIA/ODI matrix is); the field comes out "
                    f"at {g * c.field * u:.6g} mGauss, {strength}")
        out.append(ArduPilotCompass(c.instance, ofs, np.diag(M).copy(), np.array([M[0, 1], M[0, 2], M[1, 2]]),
                                    float(scale), mot, motct, c.device_id))
    note.append("ArduPilot corrects in the body frame, after COMPASS_ORIENTn / AHRS_ORIENTATION: the "
                "calibration must come from readings in that frame (no orientation is written)")
    note.append(f"the vehicle stores parameters as float32: each value is rounded to "
                f"{float32_relative_step():.1g} relative (the file itself is exact)")
    return out, note


def write(calibration, path) -> list[str]:
    compasses, note = convert(calibration)
    lines = ["# ArduPilot compass calibration written by mkc_stream (Mission Planner / MAVProxy .param)",
             "# field = DIA/ODI matrix @ (SCALE * (raw + OFS)) + MOT * (throttle or current), mGauss"]
    for c in compasses:
        names = param_names(c.instance)
        if c.device_id is not None:
            lines.append(f"# {names['DEV_ID'][0]} {c.device_id} (read-only on the vehicle: check it matches)")
        for group, values in (("OFS", c.offsets), ("DIA", c.diagonals), ("ODI", c.offdiagonals),
                              ("SCALE", [c.scale]), ("MOT", c.motor_comp)):
            lines += [f"{n},{fmt(v)}" for n, v in zip(names[group], values)]
    lines.append(f"COMPASS_MOTCT,{compasses[0].motct}")
    pathlib.Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return note


def read_values(path) -> dict:
    """NAME -> value of a .param file (NAME,VALUE or NAME VALUE per line, # comments); bad lines raise."""
    path = pathlib.Path(path)
    text = read_text(path)
    values = {}
    for no, line in enumerate(text.splitlines(), 1):
        where = f"{path}:{no}"
        body = line.strip()
        if not body or body.startswith("#"):
            continue
        fields = body.replace(",", " ").split()
        if len(fields) != 2:
            raise ParamsFileError(f"{where}: expected NAME,VALUE (got {line.strip()!r})")
        name, value = fields
        if not name.replace("_", "").isalnum() or not name[0].isalpha():
            raise ParamsFileError(f"{where}: {name!r} is not a parameter name")
        if name in values:
            raise ParamsFileError(f"{where}: {name} is set twice")
        values[name] = parse_number(value, where)
    return values


def read(path) -> list[ArduPilotCompass]:
    """The compasses a .param file calibrates (every instance with COMPASS_OFS/DIA/ODI), by instance."""
    values = read_values(path)
    comment_ids = _comment_device_ids(path)
    motct = values.get("COMPASS_MOTCT", 0.0)
    if motct not in MOTCT_NAMES:
        raise ParamsFileError(f"{path}: COMPASS_MOTCT = {motct:g} is none of {sorted(MOTCT_NAMES)} "
                              "(3, per-motor, is not supported)")
    out = []
    for k in range(MAX_INSTANCES):
        names = param_names(k)
        needed = names["OFS"] + names["DIA"] + names["ODI"]
        present = [n for n in needed if n in values]
        if not present:
            continue
        missing = [n for n in needed if n not in values]
        if missing:
            raise ParamsFileError(f"{path}: compass {k + 1} is only partly given (missing {', '.join(missing)}): "
                                  "the vehicle would mix it with the values it holds")
        dev = values.get(names["DEV_ID"][0], comment_ids.get(names["DEV_ID"][0]))
        out.append(ArduPilotCompass(
            k, np.array([values[n] for n in names["OFS"]]), np.array([values[n] for n in names["DIA"]]),
            np.array([values[n] for n in names["ODI"]]), float(values.get(names["SCALE"][0], 0.0)),
            np.array([values.get(n, 0.0) for n in names["MOT"]]), int(motct),
            None if dev is None else int(dev)))
    if not out:
        raise ParamsFileError(f"{path}: no compass calibration (COMPASS_OFS*/DIA*/ODI*) in the file")
    return out


def _comment_device_ids(path) -> dict:
    ids = {}
    for line in pathlib.Path(path).read_text(encoding="utf-8").splitlines():
        parts = line.strip().lstrip("#").split()
        if line.strip().startswith("#") and len(parts) >= 2 and parts[0].startswith("COMPASS_DEV_ID"):
            try:
                ids[parts[0]] = int(parts[1])
            except ValueError:
                pass
    return ids


def apply(compass: ArduPilotCompass, raw, current=None, throttle=None, float32: bool = False) -> np.ndarray:
    """ArduPilot's correct_field on raw body-frame readings (N, 3) in mGauss; current in A, throttle
    0..1. float32=True rounds the parameters to float32 and computes in float32, as the vehicle does."""
    dt = np.float32 if float32 else np.float64
    m = raw_array(raw).astype(dt) + compass.offsets.astype(dt)
    if SCALE_RANGE[0] <= compass.scale <= SCALE_RANGE[1]:
        m = m * dt(compass.scale)
    m = m @ compass.matrix.astype(dt).T
    thr = power_signal(throttle, "throttle", len(m), compass.motct == 1)
    cur = power_signal(current, "current", len(m), compass.motct == 2)
    signal = thr if compass.motct == 1 else cur if compass.motct == 2 else None
    if signal is not None:
        m = m + signal.astype(dt)[:, None] * compass.motor_comp.astype(dt)[None, :]
    return m.astype(float)


def output_per_unit(c: CalibrationValues) -> float:
    """mGauss per unit of the calibration: what the reference output is multiplied by to compare."""
    return c.tesla_per_unit * MG_PER_TESLA
