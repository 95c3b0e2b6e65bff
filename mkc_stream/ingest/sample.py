"""The one sample type that every source yields, and its mapping onto recording columns.

A :class:`Sample` is a NamedTuple (cheap to build a million of, immutable, compares by value).
Units are the project's: magnetometer in the source's ``units.mag`` (uT for every built-in
protocol), accelerometer m/s^2, gyroscope rad/s, temperature degC.
"""
from __future__ import annotations

import math
from typing import NamedTuple

from ..recording_rules import REQUIRED

Vec3 = tuple[float, float, float]

ACC_COLUMNS = ("ax", "ay", "az")
GYRO_COLUMNS = ("gx", "gy", "gz")


class Sample(NamedTuple):
    t: float                  # s: device clock, log time, or host receive time (then host_time=True)
    mag: Vec3                 # raw magnetometer
    acc: Vec3 | None = None   # m/s^2
    gyro: Vec3 | None = None  # rad/s
    temp: float | None = None  # degC
    seq: int | None = None    # the device's frame counter, when the protocol has one
    host_time: bool = False   # True: the device sent no time; t is when the host received it
    aux: dict | None = None   # other named signals (extra CSV columns, DBC-mapped signals)


def columns_for(samples) -> list[str]:
    """Recording columns that hold every field present in ``samples`` (first appearance order)."""
    acc = gyro = temp = seq = False
    aux: dict[str, None] = {}
    for s in samples:
        acc |= s.acc is not None
        gyro |= s.gyro is not None
        temp |= s.temp is not None
        seq |= s.seq is not None
        if s.aux:
            aux.update(dict.fromkeys(s.aux))
    cols = list(REQUIRED)           # the recorder's order: required, acc, gyro, temp, seq, auxiliary
    cols += list(ACC_COLUMNS) if acc else []
    cols += list(GYRO_COLUMNS) if gyro else []
    cols += ["temp"] if temp else []
    cols += ["seq"] if seq else []
    cols += [k for k in aux if k not in cols]
    return cols


def row_values(s: Sample, columns: list[str]) -> list[float]:
    """One sample as floats in ``columns`` order; a field the sample lacks is NaN."""
    nan = math.nan
    out = []
    for c in columns:
        if c == "t":
            out.append(s.t)
        elif c in ("mx", "my", "mz"):
            out.append(s.mag["xyz".index(c[1])])
        elif c in ACC_COLUMNS:
            out.append(nan if s.acc is None else s.acc["xyz".index(c[1])])
        elif c in GYRO_COLUMNS:
            out.append(nan if s.gyro is None else s.gyro["xyz".index(c[1])])
        elif c == "temp":
            out.append(nan if s.temp is None else s.temp)
        elif c == "seq":
            out.append(nan if s.seq is None else s.seq)
        else:
            out.append(s.aux.get(c, nan) if s.aux else nan)
    return out


def missing_fields(s: Sample, columns) -> list[str]:
    """Fields of ``s`` that ``columns`` cannot hold (a recorder reports them, never drops silently)."""
    cols = set(columns)
    out = []
    if s.acc is not None and not cols.issuperset(ACC_COLUMNS):
        out.append("acc")
    if s.gyro is not None and not cols.issuperset(GYRO_COLUMNS):
        out.append("gyro")
    if s.temp is not None and "temp" not in cols:
        out.append("temp")
    if s.seq is not None and "seq" not in cols:
        out.append("seq")
    if s.aux:
        out += [k for k in s.aux if k not in cols]
    return out
