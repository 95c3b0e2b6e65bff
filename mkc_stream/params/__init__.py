"""Parameter files the autopilots and robots load, from this package's calibration.

    note = write_params("ardupilot", CalibrationValues(b, S, F, unit="uT"), "compass.param")
    compasses = read_params("ardupilot", "compass.param")
    field_mG = apply_params("ardupilot", compasses[0], raw_mG, current=amps)

Targets: ``ardupilot`` (.param, mGauss), ``px4`` (QGroundControl .params, gauss), ``ros`` (ROS 2
parameter YAML, tesla), ``c`` (a C99 header for firmware_ref, the calibration's unit). Each module
states the target's equation, units and sign convention with the page it comes from; docs/params.md
sums them up. ``write_params`` returns the note of what the target cannot hold exactly (and prints it
to stderr); ``read_params`` parses a file back (malformed files raise ParamsFileError);
``apply_params`` corrects raw readings the way the target does.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

from . import ardupilot, c_header, px4, ros
from .model import CalibrationValues, ParamsFileError

TARGETS = {"ardupilot": ardupilot, "px4": px4, "ros": ros, "c": c_header}

__all__ = ["CalibrationValues", "ParamsFileError", "TARGETS", "WriteNote", "write_params", "read_params",
           "apply_params", "output_per_unit"]


@dataclass(frozen=True)
class WriteNote:
    """What was written where, and what the target cannot represent exactly (one line per item)."""
    target: str
    path: str
    lines: tuple

    def __str__(self) -> str:
        head = f"{self.target} parameters written to {self.path}"
        return "\n".join([head] + [f"  note: {line}" for line in self.lines])


def _module(target: str):
    try:
        return TARGETS[target]
    except KeyError:
        raise ValueError(f"unknown target {target!r}: one of {sorted(TARGETS)}") from None


def write_params(target: str, calibration, path, echo: bool = True) -> WriteNote:
    """Write `calibration` (a CalibrationValues or one per instance) as `target`'s file at `path`."""
    lines = _module(target).write(calibration, path)
    note = WriteNote(target, str(path), tuple(lines))
    if echo:
        print(note, file=sys.stderr)
    return note


def read_params(target: str, path):
    """The parameters of a `target` file: a list per instance (ardupilot, px4, c) or one object (ros)."""
    return _module(target).read(path)


def apply_params(target: str, params, raw, current=None, throttle=None, float32: bool = False):
    """Correct raw readings with parsed parameters as the target does (raw in the target's unit:
    ardupilot mGauss, px4 gauss, ros tesla, c the calibration's unit)."""
    return _module(target).apply(params, raw, current=current, throttle=throttle, float32=float32)


def output_per_unit(target: str, calibration: CalibrationValues) -> float:
    """The target's unit per unit of the calibration (e.g. 10 mGauss per uT for ardupilot)."""
    return _module(target).output_per_unit(calibration)
