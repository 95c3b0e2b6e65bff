"""ArduPilot DataFlash (``.bin``, binary ``.log``) and PX4 sdlog2 (``.px4log``) through pymavlink.

ArduPilot: one stream per compass, from ``MAG``/``MAG2``/``MAG3`` or the instance field ``I`` of
``MAG`` (newer firmware). ``MagX/Y/Z`` are milligauss (x0.1 -> uT) after the autopilot's correction
(AP_Compass): m = M (raw + ofs) + mot, with ``ofs`` the logged ``OfsX/Y/Z``, ``mot`` the logged motor
compensation ``MOfsX/Y/Z``, M the symmetric matrix of ``COMPASS_DIA*`` (diagonal) and
``COMPASS_ODI*`` (off-diagonal; identity when the diagonal is 0) and, where the log has it,
``COMPASS_SCALE*`` multiplying raw first. Undone: raw = (M^-1 (m - mot) - ofs) / scale.
Aux: ``CURR``/``BAT`` current and voltage (integer fields are centi-amps / centi-volts, as old
firmware logs them; float fields are A and V), ``CTUN.ThrOut`` (integer 0..1000 or float 0..1),
``ATT`` roll/pitch/yaw (deg) -> quaternion, ``GPS`` (status >= 3: 3D fix), ``IMU`` acc/gyro/temp.

PX4 ``.px4log``: ``IMU.MagX/Y/Z`` in gauss (x100 -> uT) with ``tM`` the magnetometer temperature,
timed by the last ``TIME.StartTime`` (us); the IMU message repeats the last magnetometer reading,
so one sample is kept per change of the reading (the repeats left out are counted in the
metadata); ``BATT`` current and voltage; ``ATT`` quaternion or Euler angles; ``GPS``. The applied
calibration (``CAL_MAGn``) is undone as in :mod:`.px4cal` where one slot is in use.

Damage: the reader skips bytes it cannot frame and says so; each such report becomes a counted
bad row, and a last message cut short is reported as truncation.
"""
from __future__ import annotations

import re

import numpy as np

from ._common import (DATAFLASH_HEAD, FlightLogError, align, align_quaternion, build_recording, captured_output, missing_library,
                      quat_from_euler, rate_of, said_lines, silenced_stderr_fd)
from .px4cal import GAUSS_TO_UT, undo_px4

MGAUSS_TO_UT = 0.1
AP_TYPES = ["MAG", "MAG2", "MAG3", "CURR", "BAT", "CTUN", "ATT", "GPS", "IMU"]
PX4_TYPES = ["TIME", "IMU", "BATT", "ATT", "GPS"]
_SKIPPED = re.compile(r"Skipped (\d+) bad bytes in log at offset (\d+)")


def _reader(path):
    try:
        from pymavlink import DFReader
    except ImportError:
        raise missing_library("dataflash") from None
    with open(path, "rb") as f:
        if f.read(2) != DATAFLASH_HEAD:
            raise FlightLogError(f"{path} is not a DataFlash or px4log file: it does not start with the "
                                 f"message header A3 95")
    with captured_output() as said, silenced_stderr_fd():
        try:
            r = DFReader.DFReader_binary(str(path), zero_time_base=False)
        except Exception as exc:  # noqa: BLE001 - pymavlink raises format-specific errors
            raise FlightLogError(f"cannot read DataFlash log {path}: {type(exc).__name__}: {exc}") from None
    return r, said.getvalue()


def _collect(r, types):
    """Every message of ``types`` as {type: [(time_s, message)]}, and what the reader said.

    The messages are parsed one after the other (recv_msg), not through pymavlink's index: the
    index stops at the first byte it cannot frame, the parser steps over it and goes on. The byte
    after the last message parsed is kept as ``r.mkc_parsed_end`` (see :func:`_damage`)."""
    wanted = set(types)
    out = {k: [] for k in types}
    px4_time = None
    r._rewind()
    r.mkc_parsed_end = r.offset
    with captured_output() as said:
        while True:
            try:
                m = r.recv_msg()
            except Exception as exc:  # noqa: BLE001 - a damaged record the reader cannot step over
                print(f"the reader stopped at byte {getattr(r, 'offset', '?')}: {type(exc).__name__}: {exc}")
                break
            if m is None:
                break
            r.mkc_parsed_end = r.offset
            name = m.get_type()
            if name not in wanted:
                continue
            if name == "TIME":
                px4_time = m.StartTime * 1e-6
                continue
            d = m.to_dict()
            if "TimeUS" in d:
                t = d["TimeUS"] * 1e-6
            elif "TimeMS" in d:
                t = d["TimeMS"] * 1e-3
            else:
                t = px4_time if px4_time is not None else np.nan
            if name == "MAG" and "I" in d:
                name = {0: "MAG", 1: "MAG2", 2: "MAG3"}.get(int(d["I"]), f"MAG{int(d['I']) + 1}")
            out.setdefault(name, []).append((t, d))
    return out, said.getvalue()


def _damage(said: str, r) -> list[tuple[int, str]]:
    out = []
    for line in said.splitlines():
        m = _SKIPPED.search(line)
        if m:
            out.append((int(m.group(2)), f"corrupt: {m.group(1)} bytes the reader could not frame, skipped at "
                                         f"byte {m.group(2)}"))
    rest = "\n".join(line for line in said.splitlines() if not _SKIPPED.search(line)
                     and not line.startswith(("bad header", "unknown msg type")))    # the index's: parsed again
    out += [(0, f"damage: the DataFlash reader says {line}") for line in said_lines(rest)]
    # the bytes after the last message parsed: the parser stops at a message cut short, and when
    # only its 3-byte header is left it has already stepped over it (its offset is then the end)
    end = getattr(r, "mkc_parsed_end", r.offset)
    left = r.data_len - end
    if left > 0:
        out.append((int(end), f"truncated: the log ends inside its last message ({left} bytes left over "
                              f"at byte {end})"))
    return out


def _column(rows, field):
    return np.array([row[1].get(field, np.nan) for row in rows], dtype=np.float64)


def _times(rows):
    return np.array([row[0] for row in rows], dtype=np.float64)


def _fmt_char(r, msg, field):
    fmt = r.formats.get(r.name_to_id.get(msg)) if msg in r.name_to_id else None
    if fmt is None or field not in fmt.columns:
        return "f"
    return fmt.format[fmt.columns.index(field)]


def _ap_matrix(params, k):
    suf = "" if k == 0 else str(k + 1)
    dia = np.array([params.get(f"COMPASS_DIA{suf}_{a}", 0.0) for a in "XYZ"], dtype=np.float64)
    odi = np.array([params.get(f"COMPASS_ODI{suf}_{a}", 0.0) for a in "XYZ"], dtype=np.float64)
    if np.all(dia == 0):
        dia = np.ones(3)
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    scale = float(params.get(f"COMPASS_SCALE{suf}", 0.0)) or 1.0
    return M, scale


def _ap_aux(r, msgs, t):
    aux = {}
    for name in ("BAT", "CURR"):
        rows = [row for row in msgs.get(name) or []            # the first battery (newer firmware: instance)
                if int(row[1].get("Instance", row[1].get("Inst", row[1].get("I", 0)))) == 0]
        if not rows:
            continue
        ts = _times(rows)
        k = 0.01 if _fmt_char(r, name, "Curr") in "hHiI" else 1.0      # centi-amps in old firmware
        aux["current"] = align(t, ts, _column(rows, "Curr") * k)
        kv = 0.01 if _fmt_char(r, name, "Volt") in "hHiI" else 1.0
        aux["voltage"] = align(t, ts, _column(rows, "Volt") * kv)
        break
    rows = msgs.get("CTUN") or []
    if rows and "ThrOut" in rows[0][1]:
        k = 1e-3 if _fmt_char(r, "CTUN", "ThrOut") in "hHiI" else 1.0
        aux["throttle"] = align(t, _times(rows), _column(rows, "ThrOut") * k)
    rows = msgs.get("ATT") or []
    if rows:
        q = quat_from_euler(*(np.radians(_column(rows, f)) for f in ("Roll", "Pitch", "Yaw")))
        q = align_quaternion(t, _times(rows), q)
        for j, col in enumerate(("qw", "qx", "qy", "qz")):
            aux[col] = q[:, j]
    rows = [row for row in msgs.get("GPS") or [] if row[1].get("Status", 0) >= 3]
    if rows:
        ts = np.array([row[1].get("TimeUS", row[1].get("T", np.nan)) for row in rows], dtype=np.float64)
        ts = ts * (1e-6 if "TimeUS" in rows[0][1] else 1e-3)
        aux["lat"] = align(t, ts, _column(rows, "Lat"))
        aux["lon"] = align(t, ts, _column(rows, "Lng"))
        aux["alt"] = align(t, ts, _column(rows, "Alt"))
    rows = [row for row in msgs.get("IMU") or [] if row[1].get("I", 0) == 0]
    if rows:
        ts = _times(rows)
        for col, f in zip(("ax", "ay", "az", "gx", "gy", "gz", "temp"),
                          ("AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ", "Temp")):
            if f in rows[0][1]:
                aux[col] = align(t, ts, _column(rows, f))
    return aux


def _ap_instances(msgs):
    return [k for k, name in enumerate(("MAG", "MAG2", "MAG3")) if msgs.get(name)]


def _ap_stream(r, msgs, inst):
    rows = msgs[("MAG", "MAG2", "MAG3")[inst]]
    t = _times(rows)
    m = np.c_[_column(rows, "MagX"), _column(rows, "MagY"), _column(rows, "MagZ")]
    ofs = np.c_[_column(rows, "OfsX"), _column(rows, "OfsY"), _column(rows, "OfsZ")]
    mot = np.nan_to_num(np.c_[_column(rows, "MOfsX"), _column(rows, "MOfsY"), _column(rows, "MOfsZ")])
    M, scale = _ap_matrix(r.params, inst)
    if np.all(np.isfinite(ofs)):
        raw = (np.linalg.solve(M, (m - mot).T).T - ofs) / scale     # undo m = M (scale raw + ofs) + mot
        note = "raw: the logged offsets (OfsX/Y/Z), motor compensation (MOfsX/Y/Z) and COMPASS_DIA/ODI were undone"
    else:
        raw, note = m, "calibrated, not undone: this firmware does not log the offsets in MAG"
    applied = {"offset_mG_first": ofs[0].tolist() if len(ofs) else None, "matrix": M.tolist(), "scale": scale,
               "motor_offset_max_mG": float(np.max(np.abs(mot))) if len(mot) else 0.0,
               "model": "m = M (scale raw + ofs) + mot"}
    return t, raw * MGAUSS_TO_UT, m * MGAUSS_TO_UT, note, applied


def _px4_stream(r, msgs):
    rows = msgs.get("IMU") or []
    t = _times(rows)
    m = np.c_[_column(rows, "MagX"), _column(rows, "MagY"), _column(rows, "MagZ")]
    new = np.ones(len(t), dtype=bool)
    new[1:] = np.any(m[1:] != m[:-1], axis=1)          # the IMU message repeats the last reading
    raw, note, applied = undo_px4("sensor_combined", None, None, r.params, m[new])
    return t[new], raw * GAUSS_TO_UT, _column(rows, "tM")[new], note, applied, int(np.count_nonzero(~new))


def _px4_aux(msgs, t):
    aux = {}
    rows = msgs.get("IMU") or []
    if rows:
        ts = _times(rows)
        for col, f in zip(("ax", "ay", "az", "gx", "gy", "gz"), ("AccX", "AccY", "AccZ", "GyroX", "GyroY", "GyroZ")):
            aux[col] = align(t, ts, _column(rows, f))
    rows = msgs.get("BATT") or []
    if rows:
        aux["current"] = align(t, _times(rows), _column(rows, "C"))
        aux["voltage"] = align(t, _times(rows), _column(rows, "V"))
    rows = msgs.get("ATT") or []
    if rows:
        q = np.c_[_column(rows, "qw"), _column(rows, "qx"), _column(rows, "qy"), _column(rows, "qz")]
        if not np.any(np.linalg.norm(q, axis=1) > 0.5):      # the quaternion is not filled in: Euler angles
            q = quat_from_euler(_column(rows, "Roll"), _column(rows, "Pitch"), _column(rows, "Yaw"))
        q = align_quaternion(t, _times(rows), q)
        for j, col in enumerate(("qw", "qx", "qy", "qz")):
            aux[col] = q[:, j]
    rows = [row for row in msgs.get("GPS") or [] if row[1].get("Fix", 0) >= 3]
    if rows:
        aux["lat"] = align(t, _times(rows), _column(rows, "Lat"))
        aux["lon"] = align(t, _times(rows), _column(rows, "Lon"))
        aux["alt"] = align(t, _times(rows), _column(rows, "Alt"))
    return aux


def _load(path):
    r, _ = _reader(path)          # what its index builder says is said again by the parser below
    px4 = "MAG" not in r.name_to_id and "IMU" in r.name_to_id and "MagX" in (
        r.formats[r.name_to_id["IMU"]].columns)
    msgs, said = _collect(r, PX4_TYPES if px4 else AP_TYPES)
    damage = _damage(said, r)
    if px4:
        if not msgs.get("IMU"):
            raise FlightLogError(f"{path}: the px4log has no IMU message with a magnetometer")
    elif not _ap_instances(msgs):
        found = sorted(r.name_to_id)
        raise FlightLogError(f"{path}: the DataFlash log has no MAG, MAG2 or MAG3 message; messages defined: "
                             f"{', '.join(found[:60]) or 'none'}")
    return r, msgs, px4, damage


def read_dataflash(path, instance=None, topic=None):
    """One compass of a DataFlash or px4log file as a :class:`~mkc_stream.io.recording.Recording` (uT)."""
    r, msgs, px4, damage = _load(path)
    params = {k: r.params[k] for k in sorted(r.params) if k.startswith(("COMPASS_", "CAL_MAG", "SENS_BOARD"))}
    meta = {"format": "PX4 sdlog2 px4log" if px4 else "ArduPilot DataFlash", "source": str(path),
            "units.mag": "uT", "time_source": "log", "units.time": "s since the autopilot's boot"}
    if px4:
        if instance not in (None, 0, "0"):
            raise FlightLogError(f"{path}: a px4log holds one magnetometer (instance 0)")
        t, mag, temp, note, applied, repeats = _px4_stream(r, msgs)
        aux = _px4_aux(msgs, t)
        aux["temp"] = temp
        meta.update({"mag.topic": "IMU.MagX/Y/Z", "mag.instance": 0, "mag.unit_in_log": "gauss (x100 -> uT)",
                     "mag.repeats_left_out": repeats})
    else:
        have = _ap_instances(msgs)
        inst = have[0] if instance is None else int(instance)
        if inst not in have:
            raise FlightLogError(f"{path}: no compass instance {inst}; instances: {have}")
        t, mag, _, note, applied = _ap_stream(r, msgs, inst)
        aux = _ap_aux(r, msgs, t)
        meta.update({"mag.topic": ("MAG", "MAG2", "MAG3")[inst], "mag.instance": inst,
                     "mag.unit_in_log": "milligauss (x0.1 -> uT)"})
    meta.update({"calibration": note, "applied_calibration": applied,
                 "attitude": "ATT (body FRD -> NED)" if "qw" in aux else "none"})
    for k, v in params.items():
        meta[f"param.{k}"] = repr(float(v))
    return build_recording(path, t, mag, aux, meta, damage)


def inspect_dataflash(path) -> dict:
    r, msgs, px4, damage = _load(path)
    out = []
    if px4:
        t, _, _, note, applied, _ = _px4_stream(r, msgs)
        streams = [(0, "IMU", t, note, applied, sorted(_px4_aux(msgs, t[:2])) + ["temp"])]
    else:
        streams = []
        for k in _ap_instances(msgs):
            t, _, _, note, applied = _ap_stream(r, msgs, k)
            streams.append((k, ("MAG", "MAG2", "MAG3")[k], t, note, applied, sorted(_ap_aux(r, msgs, t[:2]))))
    for k, name, t, note, applied, aux in streams:
        out.append({"id": k, "topic": name, "samples": int(len(t)), "rate_hz": rate_of(t),
                    "duration_s": float(t[-1] - t[0]) if len(t) else 0.0, "aux": aux,
                    "calibration": note, "applied_calibration": applied})
    return {"format": "PX4 sdlog2 px4log" if px4 else "ArduPilot DataFlash", "instances": out,
            "damage": [why for _, why in damage]}
