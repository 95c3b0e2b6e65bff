"""The calibration a parameter file is written from, its units, and the helpers every target shares.

This package's convention: ``m_cal = S (m_raw - b - k_I * current - k_T * throttle)``, with ``b`` the
hard iron and ``S`` the soft iron (symmetric positive definite, det S = 1), both in the sensor frame;
``F`` is the field strength ``|m_cal|`` the fit found. ``k_I`` (unit/A) and ``k_T`` (unit at full
throttle, throttle in 0..1) say what the power wiring adds to the raw reading (``m_raw`` contains
``+ k_I * current``). When ``expected_field`` is given (the Earth field's strength from a model, same
unit), the output is rescaled to it: ``m_out = (expected_field / F) * m_cal``; otherwise ``m_out =
m_cal``. Every target's output is ``m_out`` in that target's unit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..units import MICROTESLA

#: tesla per unit, for the units a calibration may be given in (counts have no physical scale: a
#: target that reads gauss or tesla cannot be given a calibration in counts)
TESLA_PER_UNIT = {**{u.lower(): 1e-6 for u in MICROTESLA}, "nt": 1e-9, "mg": 1e-7, "mgauss": 1e-7,
                  "g": 1e-4, "gauss": 1e-4, "t": 1.0}

#: |det S - 1| and the relative asymmetry of S accepted as "det 1, symmetric"
DET_TOLERANCE = 1e-6
SYMMETRY_TOLERANCE = 1e-9


class ParamsFileError(ValueError):
    """A parameter file that cannot be read: the message names the file, the line and what is wrong."""


@dataclass(frozen=True)
class CalibrationValues:
    """One magnetometer's calibration as plain values (see the module docstring for the equation).

    ``instance`` is 0-based (ArduPilot's first compass COMPASS_OFS_*, PX4's CAL_MAG0_*);
    ``device_id`` is the autopilot's id of the sensor (PX4 CAL_MAGn_ID, ArduPilot COMPASS_DEV_ID).
    """
    hard_iron: Sequence[float]
    soft_iron: Sequence[Sequence[float]]
    field: float
    unit: str = "uT"
    current_coeff: Optional[Sequence[float]] = None
    throttle_coeff: Optional[Sequence[float]] = None
    expected_field: Optional[float] = None
    instance: int = 0
    device_id: Optional[int] = None

    def __post_init__(self):
        b = _vector(self.hard_iron, "hard_iron")
        S = np.array(self.soft_iron, dtype=float)
        if S.shape != (3, 3) or not np.all(np.isfinite(S)):
            raise ValueError(f"soft_iron must be a finite 3x3 matrix (got shape {S.shape})")
        if np.max(np.abs(S - S.T)) > SYMMETRY_TOLERANCE * max(np.max(np.abs(S)), 1e-300):
            raise ValueError("soft_iron must be symmetric (this package's S is; an asymmetric S "
                             "has no form in the ArduPilot/PX4 parameters)")
        S = 0.5 * (S + S.T)
        eig = np.linalg.eigvalsh(S)
        if eig[0] <= 0:
            raise ValueError(f"soft_iron must be positive definite (smallest eigenvalue {eig[0]:.6g})")
        det = float(np.prod(eig))
        if abs(det - 1.0) > DET_TOLERANCE:
            raise ValueError(f"soft_iron must have det 1 in this package's convention (got {det:.9g}); "
                             "put the overall scale in `field`")
        if not (isinstance(self.field, (int, float)) and math.isfinite(self.field) and self.field > 0):
            raise ValueError(f"field must be a positive finite number (got {self.field!r})")
        if self.unit.strip().lower() not in TESLA_PER_UNIT:
            raise ValueError(f"unit {self.unit!r} is not a physical field unit "
                             f"(one of {sorted(set(TESLA_PER_UNIT))}); counts cannot be converted")
        kI = None if self.current_coeff is None else _vector(self.current_coeff, "current_coeff")
        kT = None if self.throttle_coeff is None else _vector(self.throttle_coeff, "throttle_coeff")
        if self.expected_field is not None and not (
                isinstance(self.expected_field, (int, float)) and math.isfinite(self.expected_field)
                and self.expected_field > 0):
            raise ValueError(f"expected_field must be a positive finite number (got {self.expected_field!r})")
        if not isinstance(self.instance, (int, np.integer)) or isinstance(self.instance, bool) or self.instance < 0:
            raise ValueError(f"instance must be a non-negative integer (got {self.instance!r})")
        if self.device_id is not None and (
                not isinstance(self.device_id, (int, np.integer)) or isinstance(self.device_id, bool)
                or not 0 <= self.device_id < 2 ** 32):
            raise ValueError(f"device_id must be an integer in 0..2^32-1 (got {self.device_id!r})")
        object.__setattr__(self, "hard_iron", b)
        object.__setattr__(self, "soft_iron", S)
        object.__setattr__(self, "current_coeff", kI)
        object.__setattr__(self, "throttle_coeff", kT)
        object.__setattr__(self, "instance", int(self.instance))

    @property
    def tesla_per_unit(self) -> float:
        return TESLA_PER_UNIT[self.unit.strip().lower()]

    @property
    def gain(self) -> float:
        """expected_field / F: the factor that brings |m_cal| to the expected field (1 without one)."""
        return 1.0 if self.expected_field is None else float(self.expected_field) / float(self.field)

    def output(self, raw, current=None, throttle=None) -> np.ndarray:
        """m_out = gain * S (m_raw - b - k_I current - k_T throttle), in the calibration's unit.

        raw (N, 3) in the calibration's unit; current (N,) in A; throttle (N,) in 0..1. A coefficient
        without its signal (or the reverse) is an error, not a silent zero.
        """
        m = np.atleast_2d(np.asarray(raw, dtype=float)) - self.hard_iron
        m = m - _power_term(self.current_coeff, current, "current", len(m))
        m = m - _power_term(self.throttle_coeff, throttle, "throttle", len(m))
        return self.gain * m @ self.soft_iron.T


def _vector(v, name) -> np.ndarray:
    a = np.array(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers (got {v!r})")
    return a


def _power_term(coeff, signal, name, n) -> np.ndarray:
    if coeff is None and signal is None:
        return np.zeros(3)
    if coeff is None:
        return np.zeros(3)          # a signal without a coefficient: nothing to compensate
    if signal is None:
        raise ValueError(f"the calibration has a {name} coefficient: give the {name} signal")
    s = np.asarray(signal, dtype=float).reshape(-1)
    if s.shape != (n,):
        raise ValueError(f"{name} must have one value per sample ({n}), got shape {np.shape(signal)}")
    return s[:, None] * coeff[None, :]


def power_signal(signal, name, n, required: bool):
    """The (n,) float array of a power signal, or None when not needed; a needed missing one is an error."""
    if not required:
        return None
    if signal is None:
        raise ValueError(f"the parameters compensate with {name}: give the {name} signal")
    s = np.asarray(signal, dtype=float).reshape(-1)
    if s.shape != (n,):
        raise ValueError(f"{name} must have one value per sample ({n}), got shape {np.shape(signal)}")
    return s


def raw_array(raw) -> np.ndarray:
    m = np.atleast_2d(np.asarray(raw, dtype=float))
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"raw must be (N, 3) (got shape {np.shape(raw)})")
    return m


def as_list(calibration) -> list[CalibrationValues]:
    """One calibration or several (one per instance, instances distinct), as a list."""
    cals = [calibration] if isinstance(calibration, CalibrationValues) else list(calibration)
    if not cals or not all(isinstance(c, CalibrationValues) for c in cals):
        raise ValueError("give a CalibrationValues or a non-empty sequence of them")
    instances = [c.instance for c in cals]
    if len(set(instances)) != len(instances):
        raise ValueError(f"each calibration needs its own instance (got {instances})")
    return sorted(cals, key=lambda c: c.instance)


def fmt(x: float) -> str:
    """A float written so that it reads back to the same float64, without an exponent (some ground
    stations' readers are plain decimal)."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot write a non-finite value {x!r}")
    return np.format_float_positional(x, unique=True, trim="0")


def parse_number(text: str, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ParamsFileError(f"{where}: value {text!r} is not a number") from None
    if not math.isfinite(v):
        raise ParamsFileError(f"{where}: value {text!r} is not finite")
    return v


def max_direction_change_deg(M: np.ndarray) -> float:
    """The largest angle between u and M u over all directions u, for symmetric positive definite M:
    arcsin((l_max - l_min) / (l_max + l_min)) with l the eigenvalues (the Kantorovich bound, attained)."""
    eig = np.linalg.eigvalsh(0.5 * (M + M.T))
    return math.degrees(math.asin((eig[-1] - eig[0]) / (eig[-1] + eig[0])))


def float32_relative_step() -> float:
    """The relative rounding of a float32 parameter: 2^-24 (about 6e-8)."""
    return float(np.finfo(np.float32).eps) / 2


def read_text(path) -> str:
    """A parameter file's text; ParamsFileError when it cannot be read as UTF-8."""
    import pathlib

    path = pathlib.Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ParamsFileError(f"{path}: cannot read ({e})") from None


def compensation_type(cals) -> int:
    """The autopilots' compensation selector: 2 current, 1 throttle, 0 none. One signal serves every
    compass (ArduPilot COMPASS_MOTCT, PX4 CAL_MAG_COMP_TYP), current first when any has it."""
    if any(c.current_coeff is not None for c in cals):
        return 2
    return 1 if any(c.throttle_coeff is not None for c in cals) else 0


def check_instances(cals, limit: int, target: str) -> None:
    bad = [c.instance for c in cals if c.instance >= limit]
    if bad:
        raise ValueError(f"{target} has calibration parameters for instances 0..{limit - 1} only (got {bad})")
