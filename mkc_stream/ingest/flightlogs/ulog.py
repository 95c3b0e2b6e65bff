"""PX4 ULog (``.ulg``) through pyulog.

The magnetometer comes from the first topic of MAG_TOPICS the log has: ``sensor_mag`` (one stream
per instance, with ``device_id`` and temperature), else ``vehicle_magnetometer`` (the autopilot's
selected, calibrated field), else the ``magnetometer_ga`` of ``sensor_combined`` (older PX4; the
topic is logged faster than the magnetometer, so one sample is kept per distinct magnetometer time).
PX4 logs gauss; the recording holds uT (1 G = 100 uT).

Applied calibration: see :mod:`.px4cal`. Checked on the v1.11.2 log of the pyulog sample:
``sensor_mag`` instance 1 is bit-identical to ``vehicle_magnetometer`` and reads 44 uT, where
undoing CAL_MAG1 gives 77 uT and applying it again 85 uT, so that ``sensor_mag`` was already
calibrated by its driver.
"""
from __future__ import annotations

import pathlib

import numpy as np

from ._common import (FlightLogError, align, align_quaternion, build_recording, captured_output, missing_library, rate_of,
                      said_lines)
from .px4cal import GAUSS_TO_UT, undo_px4

MAG_TOPICS = ("sensor_mag", "vehicle_magnetometer", "sensor_combined")
AUX_TOPICS = ("sensor_combined", "battery_status", "vehicle_attitude", "vehicle_gps_position", "sensor_gps",
              "actuator_controls_0", "vehicle_thrust_setpoint", "esc_status")
#: esc_status holds at most this many ESCs
MAX_ESCS = 8
#: sensor_combined's "no magnetometer sample" value of magnetometer_timestamp_relative
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF


def _open(path):
    try:
        from pyulog import ULog
    except ImportError:
        raise missing_library("ulog") from None
    with captured_output() as said:
        try:
            ulog = ULog(str(path), list(dict.fromkeys(MAG_TOPICS + AUX_TOPICS)))
        except Exception as exc:  # noqa: BLE001 - pyulog raises format-specific errors
            raise FlightLogError(f"cannot read ULog {path}: {type(exc).__name__}: {exc}") from None
    return ulog, said.getvalue()


#: ULog message types (the format's one-letter codes); another byte there means the walk is lost
ULOG_TYPES = frozenset(b"BFIMPQADRLCSO")
ULOG_HEADER = 16


def walk(path) -> tuple[int | None, int, float]:
    """(byte where a message is cut short by the end of the file or None, the logger's dropout
    messages, their total ms), from the message headers (uint16 size, uint8 type)."""
    import struct

    data = pathlib.Path(path).read_bytes()
    pos, n, dropouts, lost_ms = ULOG_HEADER, len(data), 0, 0.0
    while pos + 3 <= n:
        size, kind = struct.unpack_from("<HB", data, pos)
        if kind not in ULOG_TYPES:
            return None, dropouts, lost_ms            # damage: pyulog's resync reports it
        if pos + 3 + size > n:
            return pos, dropouts, lost_ms
        if kind == ord("O") and size >= 2:
            dropouts += 1
            lost_ms += struct.unpack_from("<H", data, pos + 3)[0]
        pos += 3 + size
    return (pos if pos < n else None), dropouts, lost_ms


def _damage(ulog, said: str, path=None) -> list[tuple[int, str]]:
    out = []
    if path is not None:
        cut, _, _ = walk(path)
        if cut is not None:
            out.append((cut, f"truncated: the log ends inside a message (byte {cut}); the messages before it are read"))
    if getattr(ulog, "file_corruption", False):
        out.append((0, "corrupt: pyulog found damaged data and skipped it (the samples it could "
                        "read are kept; how many were lost is unknown)"))
    out += [(0, f"damage: the ULog reader says {line}") for line in said_lines(said)]
    return out


def _version(ulog) -> tuple[int, int] | None:
    v = ulog.msg_info_dict.get("ver_sw_release")
    if not isinstance(v, int) or v == 0:
        return None
    return (v >> 24) & 0xFF, (v >> 16) & 0xFF


def _datasets(ulog, name):
    return sorted((d for d in ulog.data_list if d.name == name), key=lambda d: d.multi_id)


def _mag_topic(ulog, path, said=""):
    for name in MAG_TOPICS:
        sets = _datasets(ulog, name)
        if name == "sensor_combined":
            sets = [d for d in sets if "magnetometer_ga[0]" in d.data]
        if sets:
            return name, sets
    found = sorted({d.name for d in ulog.data_list})
    damage = "; ".join(why for _, why in _damage(ulog, said))
    raise FlightLogError(f"{path}: the ULog has no magnetometer topic ({', '.join(MAG_TOPICS)}); "
                         f"topics read: {', '.join(found) or 'none'}" + (f" ({damage})" if damage else ""))


def _mag_samples(name, ds):
    """(t s, mag G (n, 3), temperature degC or None, device_id or None) of one dataset."""
    d = ds.data
    if name == "sensor_mag":
        ts = d.get("timestamp_sample", d["timestamp"]).astype(np.float64)
        ts = np.where(ts > 0, ts, d["timestamp"])
        temp = d.get("temperature")
        dev = int(d["device_id"][0]) if "device_id" in d and len(d["device_id"]) else None
        return ts * 1e-6, np.c_[d["x"], d["y"], d["z"]].astype(np.float64), temp, dev
    if name == "vehicle_magnetometer":
        ts = d.get("timestamp_sample", d["timestamp"]).astype(np.float64)
        dev = int(d["device_id"][0]) if "device_id" in d and len(d["device_id"]) else None
        return ts * 1e-6, np.c_[d["magnetometer_ga[0]"], d["magnetometer_ga[1]"], d["magnetometer_ga[2]"]], None, dev
    rel = d["magnetometer_timestamp_relative"].astype(np.int64)
    ok = rel != RELATIVE_TIMESTAMP_INVALID
    ts = (d["timestamp"].astype(np.int64) + rel)[ok]
    m = np.c_[d["magnetometer_ga[0]"], d["magnetometer_ga[1]"], d["magnetometer_ga[2]"]][ok]
    first = np.ones(ts.shape[0], dtype=bool)
    first[1:] = ts[1:] != ts[:-1]               # the same magnetometer sample, logged again
    return ts[first] * 1e-6, m[first].astype(np.float64), None, None


def _aux(ulog, t):
    """Signals aligned onto the magnetometer times ``t`` (s), in the recording's columns."""
    aux = {}
    sc = _datasets(ulog, "sensor_combined")
    if sc:
        d = sc[0].data
        ts = d["timestamp"] * 1e-6
        for col, field in zip(("ax", "ay", "az"), ("accelerometer_m_s2[0]", "accelerometer_m_s2[1]",
                                                   "accelerometer_m_s2[2]")):
            if field in d:
                aux[col] = align(t, ts, d[field])
        for col, field in zip(("gx", "gy", "gz"), ("gyro_rad[0]", "gyro_rad[1]", "gyro_rad[2]")):
            if field in d:
                aux[col] = align(t, ts, d[field])
    bat = _datasets(ulog, "battery_status")
    if bat:
        d = bat[0].data
        if "current_a" in d:
            cur = np.where(d["current_a"] >= 0, d["current_a"], np.nan)   # PX4 logs -1 for unknown
            aux["current"] = align(t, d["timestamp"] * 1e-6, cur)
        if "voltage_v" in d:
            aux["voltage"] = align(t, d["timestamp"] * 1e-6, np.where(d["voltage_v"] > 0, d["voltage_v"], np.nan))
    act = _datasets(ulog, "actuator_controls_0")
    thrust = _datasets(ulog, "vehicle_thrust_setpoint")
    if act and "control[3]" in act[0].data:
        aux["throttle"] = align(t, act[0].data["timestamp"] * 1e-6, act[0].data["control[3]"])
    elif thrust and "xyz[2]" in thrust[0].data:          # newer PX4: thrust along -z (FRD), 0..1
        aux["throttle"] = align(t, thrust[0].data["timestamp"] * 1e-6, -thrust[0].data["xyz[2]"])
    esc = _datasets(ulog, "esc_status")
    if esc:                                              # per-ESC current (A): one column per ESC reporting
        d = esc[0].data
        count = int(np.max(d["esc_count"])) if "esc_count" in d and len(d["esc_count"]) else 0
        for k in range(min(count, MAX_ESCS)):
            field = f"esc[{k}].esc_current"
            if field in d:
                aux[f"current_esc{k}"] = align(t, d["timestamp"] * 1e-6, d[field])
    att = _datasets(ulog, "vehicle_attitude")
    if att:
        d = att[0].data
        q = align_quaternion(t, d["timestamp"] * 1e-6, np.c_[d["q[0]"], d["q[1]"], d["q[2]"], d["q[3]"]])
        for j, col in enumerate(("qw", "qx", "qy", "qz")):
            aux[col] = q[:, j]
    for name in ("vehicle_gps_position", "sensor_gps"):
        gps = _datasets(ulog, name)
        if not gps:
            continue
        d = gps[0].data
        ts = d["timestamp"] * 1e-6
        if "latitude_deg" in d:
            lat, lon, alt = d["latitude_deg"], d["longitude_deg"], d["altitude_msl_m"]
        else:                                  # int 1e-7 deg and mm
            lat, lon, alt = d["lat"] * 1e-7, d["lon"] * 1e-7, d["alt"] * 1e-3
        fix = d.get("fix_type")
        good = (fix >= 2) if fix is not None else np.ones(len(ts), dtype=bool)
        aux["lat"] = align(t, ts[good], np.asarray(lat)[good])
        aux["lon"] = align(t, ts[good], np.asarray(lon)[good])
        aux["alt"] = align(t, ts[good], np.asarray(alt)[good])
        break
    return aux


def _instances(ulog, path, said):
    name, sets = _mag_topic(ulog, path, said)
    return name, {ds.multi_id: ds for ds in sets}


def read_ulog(path, instance=None, topic=None):
    """One magnetometer instance of a ULog as a :class:`~mkc_stream.io.recording.Recording` (uT)."""
    ulog, said = _open(path)
    name, sets = _instances(ulog, path, said)
    if topic is not None and topic != name:
        raise FlightLogError(f"{path}: topic {topic!r} is not used; the magnetometer topic of this log is {name}")
    inst = min(sets) if instance is None else int(instance)
    if inst not in sets:
        raise FlightLogError(f"{path}: no {name} instance {inst}; instances: {sorted(sets)}")
    t, mag, temp, dev = _mag_samples(name, sets[inst])
    params = dict(ulog.initial_parameters)
    version = _version(ulog)
    mag, note, applied = undo_px4(name, version, dev, params, mag)
    aux = _aux(ulog, t)
    if temp is not None and np.any(np.isfinite(temp)):
        aux["temp"] = np.asarray(temp, dtype=np.float64)
    meta = {"format": "PX4 ULog", "source": str(path), "units.mag": "uT", "mag.topic": name,
            "mag.instance": inst, "mag.unit_in_log": "gauss (x100 -> uT)", "calibration": note,
            "time_source": "log", "units.time": "s since the autopilot's boot",
            "px4_version": "unknown" if version is None else f"{version[0]}.{version[1]}",
            "attitude": "vehicle_attitude q (body FRD -> NED)" if "qw" in aux else "none"}
    if dev is not None:
        meta["mag.device_id"] = dev
    if applied:
        meta["applied_calibration"] = applied
    for k in sorted(params):
        if k.startswith("CAL_MAG"):
            meta[f"param.{k}"] = repr(params[k])
    _, dropouts, lost_ms = walk(path)
    meta["logger_dropouts"] = f"{dropouts} ({lost_ms:g} ms of data the logger could not write)"
    return build_recording(path, t, mag * GAUSS_TO_UT, aux, meta, _damage(ulog, said, path))


def inspect_ulog(path) -> dict:
    ulog, said = _open(path)
    name, sets = _instances(ulog, path, said)
    version = _version(ulog)
    params = dict(ulog.initial_parameters)
    out = []
    for inst, ds in sorted(sets.items()):
        t, mag, temp, dev = _mag_samples(name, ds)
        _, note, applied = undo_px4(name, version, dev, params, mag)
        aux = sorted(_aux(ulog, t[:2]).keys()) + (["temp"] if temp is not None and np.any(np.isfinite(temp)) else [])
        out.append({"id": inst, "topic": name, "device_id": dev, "samples": int(len(t)), "rate_hz": rate_of(t),
                    "duration_s": float(t[-1] - t[0]) if len(t) else 0.0, "aux": aux,
                    "calibration": note, "applied_calibration": applied})
    return {"format": "PX4 ULog", "instances": out, "damage": [r for _, r in _damage(ulog, said, path)]}
