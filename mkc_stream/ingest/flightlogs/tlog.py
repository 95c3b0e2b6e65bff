"""MAVLink telemetry logs (``.tlog``: what a ground station records) through pymavlink.

Each magnetometer message kind is one stream, in the order of MAG_MESSAGES (``RAW_IMU``,
``SCALED_IMU``, ``SCALED_IMU2``, ``SCALED_IMU3`` in milligauss, x0.1 -> uT; ``HIGHRES_IMU`` in
gauss, x100), timed by the message's own boot time (``time_usec`` or ``time_boot_ms``). Aux on
the same clock: ``ATTITUDE`` (rad -> quaternion) or ``ATTITUDE_QUATERNION``; the messages without
a boot time (``SYS_STATUS`` current cA and voltage mV, ``BATTERY_STATUS`` current cA, -1 = unknown;
``GPS_RAW_INT`` degE7 and mm) are put on it by the median offset between the boot times and the
log's receive times. The IMU messages' own acceleration (mG -> m/s^2) and rate (mrad/s -> rad/s,
HIGHRES_IMU: SI) and temperature (cdegC) come with each sample.

Applied calibration: ArduPilot sends the corrected field (``RAW_IMU`` compass 0, ``SCALED_IMU2``
compass 1, ``SCALED_IMU3`` compass 2). Where the log holds that compass's ``COMPASS_OFS*`` (and
``COMPASS_DIA*``/``ODI*``) as PARAM_VALUE and motor compensation is off (``COMPASS_MOTCT`` = 0),
raw = M^-1 m - ofs is restored as for DataFlash; otherwise, and for PX4, the data stays as sent.
Damage: every message pymavlink cannot decode (bad CRC, cut) is counted.
"""
from __future__ import annotations

import pathlib

import numpy as np

from ._common import (FlightLogError, align, align_quaternion, build_recording, captured_output, missing_library,
                      quat_from_euler, rate_of, said_lines)

MAG_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU")
AUX_MESSAGES = ("ATTITUDE", "ATTITUDE_QUATERNION", "SYS_STATUS", "BATTERY_STATUS", "GPS_RAW_INT", "PARAM_VALUE",
                "HEARTBEAT")
#: ArduPilot: the compass whose corrected field each message carries
AP_COMPASS = {"RAW_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
G0 = 9.80665
#: milligauss -> uT
MG_TO_UT = 0.1


#: the longest MAVLink 2 frame: 10 header + 255 payload + 2 checksum + 13 signature bytes
MAX_FRAME = 280


def _collect(path):
    try:
        from pymavlink import mavutil
    except ImportError:
        raise missing_library("tlog") from None
    wanted = set(MAG_MESSAGES + AUX_MESSAGES)
    msgs: dict[str, list] = {k: [] for k in wanted}
    bad: list[tuple[int, str]] = []
    with captured_output() as said:
        try:
            conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
        except Exception as exc:  # noqa: BLE001
            raise FlightLogError(f"cannot read the telemetry log {path}: {type(exc).__name__}: {exc}") from None
        try:
            n = 0
            whole = 0              # bytes of the complete records read: 8-byte time stamp + frame each
            while True:
                try:
                    m = conn.recv_msg()
                except Exception as exc:  # noqa: BLE001 - a record the parser cannot step over
                    bad.append((n, f"corrupt: the MAVLink parser stopped: {type(exc).__name__}: {exc}"))
                    break
                if m is None:
                    break
                n += 1
                kind = m.get_type()
                if kind != "BAD_DATA":
                    whole += 8 + len(m.get_msgbuf())
                if kind == "BAD_DATA":
                    bad.append((n, f"corrupt: a MAVLink message that does not decode "
                                   f"({str(getattr(m, 'reason', ''))[:60]})"))
                elif kind in wanted:
                    msgs[kind].append((getattr(m, "_timestamp", np.nan), m.to_dict()))
        finally:
            conn.close()
    # pymavlink passes over a record cut by the end of the file without a word
    tail = pathlib.Path(path).stat().st_size - whole
    if not bad and 0 < tail < 8 + MAX_FRAME:
        bad.append((n, f"truncated: the log ends inside a record ({tail} bytes after the last whole one)"))
    bad += [(0, f"damage: the MAVLink reader says {line}") for line in said_lines(said.getvalue())]
    return msgs, bad


def _boot_time(d):
    """The message's time since the autopilot's boot (s)."""
    if "time_usec" in d:
        return d["time_usec"] * 1e-6
    return d["time_boot_ms"] * 1e-3


def _params(msgs):
    out = {}
    for _, d in msgs["PARAM_VALUE"]:
        name = d["param_id"]
        name = name.decode(errors="replace") if isinstance(name, bytes) else str(name)
        out[name.rstrip("\x00")] = float(d["param_value"])
    return out


def _streams(msgs):
    return [k for k in MAG_MESSAGES if msgs[k]]


def _undo(kind, msgs, params, m_mg):
    ardupilot = any(d.get("autopilot") == MAV_AUTOPILOT_ARDUPILOTMEGA for _, d in msgs["HEARTBEAT"])
    if not ardupilot or kind not in AP_COMPASS:
        return m_mg, "as sent, not undone (not an ArduPilot compass message)", None
    k = AP_COMPASS[kind]
    suf = "" if k == 0 else str(k + 1)
    if f"COMPASS_OFS{suf}_X" not in params:
        return m_mg, f"as sent (corrected), not undone: the log has no COMPASS_OFS{suf}_* parameter", None
    if params.get("COMPASS_MOTCT", 0.0) != 0.0:
        return m_mg, "as sent (corrected), not undone: motor compensation is on and not in the telemetry", None
    ofs = np.array([params[f"COMPASS_OFS{suf}_{a}"] for a in "XYZ"])
    dia = np.array([params.get(f"COMPASS_DIA{suf}_{a}", 0.0) for a in "XYZ"])
    odi = np.array([params.get(f"COMPASS_ODI{suf}_{a}", 0.0) for a in "XYZ"])
    if np.all(dia == 0):
        dia = np.ones(3)
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    raw = np.linalg.solve(M, m_mg.T).T - ofs                 # undo m = M (raw + ofs)
    applied = {"offset_mG": ofs.tolist(), "matrix": M.tolist(), "model": "m = M (raw + ofs)"}
    return raw, f"raw: COMPASS_OFS{suf}/DIA{suf}/ODI{suf} from the log's parameters were undone", applied


def imu_arrays(kind, rows):
    """One IMU message kind's rows ``[(receive_time, message dict), ...]`` as arrays: boot time (s),
    receive time, magnetometer (milligauss; x MG_TO_UT -> uT) and ``ax..gz``/``temp`` in the
    recording's units. Shared by the .tlog reader and the live link, so both convert alike."""
    t = np.array([_boot_time(d) for _, d in rows], dtype=np.float64)
    recv = np.array([r for r, _ in rows], dtype=np.float64)
    col = lambda f: np.array([d.get(f, np.nan) for _, d in rows], dtype=np.float64)  # noqa: E731
    mag = np.c_[col("xmag"), col("ymag"), col("zmag")]
    aux = {}
    if kind == "HIGHRES_IMU":
        mag = mag * 1000.0                                    # gauss -> milligauss
        for c, f in zip(("ax", "ay", "az", "gx", "gy", "gz"), ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro")):
            aux[c] = col(f)
        aux["temp"] = col("temperature")
    else:
        for c, f in zip(("ax", "ay", "az"), ("xacc", "yacc", "zacc")):
            aux[c] = col(f) * 1e-3 * G0                        # mG -> m/s^2
        for c, f in zip(("gx", "gy", "gz"), ("xgyro", "ygyro", "zgyro")):
            aux[c] = col(f) * 1e-3                             # mrad/s -> rad/s
        if rows and "temperature" in rows[0][1]:
            temp = col("temperature")
            aux["temp"] = np.where(temp == 0, np.nan, temp * 0.01)   # cdegC; 0 = not sent
    return t, recv, mag, aux


def battery_current_a(centi_amps):
    """BATTERY_STATUS/SYS_STATUS ``current_battery`` (cA, -1 = unknown) -> A."""
    cur = np.asarray(centi_amps, dtype=np.float64)
    return np.where(cur < 0, np.nan, cur * 0.01)


def battery_voltage_v(millivolts):
    """SYS_STATUS ``voltage_battery`` (mV, 65535 = unknown) -> V."""
    v = np.asarray(millivolts, dtype=np.float64)
    return np.where(v >= 65535, np.nan, v * 1e-3)


def gps_position(lat_e7, lon_e7, alt_mm):
    """GPS_RAW_INT degE7, degE7, mm -> (lat deg, lon deg, alt m above mean sea level)."""
    return (np.asarray(lat_e7) * 1e-7, np.asarray(lon_e7) * 1e-7, np.asarray(alt_mm) * 1e-3)


def _aux(msgs, t, offset):
    aux = {}
    if msgs["ATTITUDE_QUATERNION"]:
        rows = msgs["ATTITUDE_QUATERNION"]
        q = np.array([[d["q1"], d["q2"], d["q3"], d["q4"]] for _, d in rows], dtype=np.float64)
        q = align_quaternion(t, [_boot_time(d) for _, d in rows], q)
    elif msgs["ATTITUDE"]:
        rows = msgs["ATTITUDE"]
        e = np.array([[d["roll"], d["pitch"], d["yaw"]] for _, d in rows], dtype=np.float64)
        q = align_quaternion(t, [_boot_time(d) for _, d in rows], quat_from_euler(e[:, 0], e[:, 1], e[:, 2]))
    else:
        q = None
    if q is not None:
        for j, c in enumerate(("qw", "qx", "qy", "qz")):
            aux[c] = q[:, j]
    on_boot = lambda rows: np.array([r for r, _ in rows], dtype=np.float64) + offset  # noqa: E731
    for kind in ("BATTERY_STATUS", "SYS_STATUS"):
        rows = msgs[kind]
        if rows:
            cur = battery_current_a([d["current_battery"] for _, d in rows])
            aux["current"] = align(t, on_boot(rows), cur)
            if kind == "SYS_STATUS":
                aux["voltage"] = align(t, on_boot(rows), battery_voltage_v([d["voltage_battery"] for _, d in rows]))
            break
    rows = [(r, d) for r, d in msgs["GPS_RAW_INT"] if d["fix_type"] >= 3]
    if rows:
        tb = on_boot(rows)
        pos = gps_position(*(np.array([d[f] for _, d in rows]) for f in ("lat", "lon", "alt")))
        for c, v in zip(("lat", "lon", "alt"), pos):
            aux[c] = align(t, tb, v)
    return aux


def _load(path):
    msgs, bad = _collect(path)
    if not _streams(msgs):
        seen = sorted(k for k, v in msgs.items() if v)
        raise FlightLogError(f"{path}: the telemetry log has no magnetometer message ({', '.join(MAG_MESSAGES)}); "
                             f"messages read: {', '.join(seen) or 'none'}")
    return msgs, bad


def read_tlog(path, instance=None, topic=None):
    """One magnetometer message kind of a .tlog as a :class:`~mkc_stream.io.recording.Recording` (uT)."""
    msgs, bad = _load(path)
    kinds = _streams(msgs)
    if topic is not None:
        if topic not in kinds:
            raise FlightLogError(f"{path}: no {topic} messages; magnetometer messages: {', '.join(kinds)}")
        k = kinds.index(topic)
    else:
        k = 0 if instance is None else int(instance)
        if not 0 <= k < len(kinds):
            raise FlightLogError(f"{path}: no instance {k}; instances: "
                                 f"{', '.join(f'{i}={n}' for i, n in enumerate(kinds))}")
    kind = kinds[k]
    t, recv, mag_mg, aux = imu_arrays(kind, msgs[kind])
    params = _params(msgs)
    raw, note, applied = _undo(kind, msgs, params, mag_mg)
    offset = float(np.nanmedian(t - recv)) if len(t) else 0.0
    aux.update(_aux(msgs, t, offset))
    meta = {"format": "MAVLink telemetry log", "source": str(path), "units.mag": "uT", "mag.topic": kind,
            "mag.instance": k, "mag.unit_in_log": "gauss (x100 -> uT)" if kind == "HIGHRES_IMU" else
            "milligauss (x0.1 -> uT)", "calibration": note, "time_source": "log",
            "units.time": "s since the autopilot's boot", "attitude": "ATTITUDE (body FRD -> NED)" if "qw" in aux
            else "none"}
    if applied:
        meta["applied_calibration"] = applied
    for name in sorted(params):
        if name.startswith("COMPASS_"):
            meta[f"param.{name}"] = repr(params[name])
    return build_recording(path, t, raw * MG_TO_UT, aux, meta, bad)


def inspect_tlog(path) -> dict:
    msgs, bad = _load(path)
    params = _params(msgs)
    out = []
    for k, kind in enumerate(_streams(msgs)):
        t, recv, mag_mg, aux = imu_arrays(kind, msgs[kind])
        _, note, applied = _undo(kind, msgs, params, mag_mg)
        out.append({"id": k, "topic": kind, "samples": int(len(t)), "rate_hz": rate_of(t),
                    "duration_s": float(t[-1] - t[0]) if len(t) else 0.0,
                    "aux": sorted(set(aux) | set(_aux(msgs, t[:2], 0.0))), "calibration": note,
                    "applied_calibration": applied})
    return {"format": "MAVLink telemetry log", "instances": out, "damage": [w for _, w in bad]}
