"""ROS 1 bags (``.bag``) and ROS 2 bags (a folder with ``metadata.yaml`` and ``.db3`` or ``.mcap``
files, given as the folder or a file in it) through rosbags, which needs no ROS install.

The magnetometer topic is the one named by ``topic=``, else the ``instance``-th (default 0) topic
of type ``sensor_msgs/MagneticField`` (tesla -> x1e6 uT), else of ``geometry_msgs/Vector3Stamped``
whose name mentions "mag" (no unit in the message: ``units.mag`` is ``raw``). Time is the header
stamp (the bag's receive time where the stamp is zero). Aux: ``sensor_msgs/Imu`` (m/s^2, rad/s;
its orientation, body FLU -> ENU in ROS's convention, becomes body -> NED:
q = q_NED<-ENU q_ROS), ``sensor_msgs/Temperature`` (degC), ``sensor_msgs/BatteryState``
(A, V), ``sensor_msgs/NavSatFix`` (``lat, lon`` and ``alt_wgs84``: its altitude is above the
ellipsoid, not sea level); each the first topic of its type, aligned onto the magnetometer's times.
"""
from __future__ import annotations

import pathlib

import numpy as np

from ._common import FlightLogError, align, align_quaternion, build_recording, missing_library, rate_of

MAG_FIELD = "sensor_msgs/msg/MagneticField"
VECTOR3 = "geometry_msgs/msg/Vector3Stamped"
IMU = "sensor_msgs/msg/Imu"
TEMPERATURE = "sensor_msgs/msg/Temperature"
BATTERY = "sensor_msgs/msg/BatteryState"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
TESLA_TO_UT = 1e6
#: q_NED<-ENU: the rotation that swaps x and y and flips z (180 deg about (1, 1, 0) / sqrt 2)
Q_NED_ENU = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5), 0.0])


def bag_path(path) -> pathlib.Path:
    """The bag to open: a ROS 2 bag's folder for a file inside it."""
    path = pathlib.Path(path)
    if path.is_file() and path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def _open(path):
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise missing_library("rosbag1" if pathlib.Path(path).suffix.lower() == ".bag" else "rosbag2") from None
    reader = AnyReader([bag_path(path)])
    try:
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises format-specific errors
        salvage = _salvage(path)
        if salvage is None:
            raise FlightLogError(f"cannot read the bag {path}: {type(exc).__name__}: {exc}") from None
        return salvage
    return reader


def _salvage(path):
    """The messages of a cut MCAP or ROS 1 bag before the damage (mcap_salvage.py, ros1_salvage.py), or
    None when there are none."""
    from .mcap_salvage import McapSalvageReader
    from .ros1_salvage import Ros1SalvageReader

    bag = bag_path(path)
    if bag.is_file() and bag.suffix.lower() == ".bag":
        files, Reader = [bag], Ros1SalvageReader
    else:
        files = sorted(bag.glob("*.mcap")) if bag.is_dir() else ([bag] if bag.suffix.lower() == ".mcap" else [])
        Reader = McapSalvageReader
    if len(files) != 1:
        return None
    try:
        reader = Reader(files[0])
    except (OSError, ValueError):
        return None
    if not reader.connections:
        return None
    # rosbags refused the file although every record up to the data end reads: the summary is cut
    reader.summary_only = not reader.stopped
    return reader


def _truncation(reader, n, damage):
    """A salvaged reader's cut, counted once where the samples end."""
    if getattr(reader, "summary_only", False):
        damage.append((n, "truncated: the bag's summary section after its data is cut or damaged; every message is kept"))
    elif getattr(reader, "stopped", ""):
        lost = f", {reader.lost_chunks} compressed chunk(s) lost" if reader.lost_chunks else ""
        damage.append((n, f"truncated: the bag ends in a {reader.stopped}{lost}; the messages before it are kept"))


def _stamp(msg, bag_ns):
    h = getattr(msg, "header", None)
    if h is not None and (h.stamp.sec or h.stamp.nanosec):
        return h.stamp.sec + h.stamp.nanosec * 1e-9
    return bag_ns * 1e-9


def _read(reader, conns, fields, damage):
    """(t (n,), values (n, k)) of every message on ``conns``; damaged messages are counted."""
    t, rows = [], []
    it = reader.messages(connections=conns)
    while True:
        try:
            conn, ns, raw = next(it)
        except StopIteration:
            break
        except Exception as exc:  # noqa: BLE001 - a damaged chunk ends the reading
            damage.append((len(t), f"corrupt: the bag reader stopped: {type(exc).__name__}: {str(exc)[:100]}"))
            break
        try:
            msg = reader.deserialize(raw, conn.msgtype)
            vals = [_get(msg, f) for f in fields]
        except Exception as exc:  # noqa: BLE001 - one message that does not decode
            damage.append((len(t), f"corrupt: a {conn.msgtype} message does not decode: {str(exc)[:100]}"))
            continue
        t.append(_stamp(msg, ns))
        rows.append(vals)
    return np.array(t, dtype=np.float64), np.array(rows, dtype=np.float64).reshape(len(rows), len(fields))


def _get(msg, dotted):
    for part in dotted.split("."):
        msg = getattr(msg, part)
    return float(msg)


def _candidates(reader):
    conns = reader.connections
    mags = sorted({c.topic for c in conns if c.msgtype == MAG_FIELD})
    if not mags:
        mags = sorted({c.topic for c in conns if c.msgtype == VECTOR3 and "mag" in c.topic.lower()})
    return mags


def _topics_text(reader):
    return ", ".join(f"{c.topic} ({c.msgtype})" for c in sorted(reader.connections, key=lambda c: c.topic)) or "none"


def _first_of(reader, msgtype):
    return sorted((c for c in reader.connections if c.msgtype == msgtype), key=lambda c: c.topic)[:1]


def _aux(reader, t, damage):
    aux = {}
    imu = _first_of(reader, IMU)
    if imu:
        fields = ["linear_acceleration.x", "linear_acceleration.y", "linear_acceleration.z",
                  "angular_velocity.x", "angular_velocity.y", "angular_velocity.z",
                  "orientation.w", "orientation.x", "orientation.y", "orientation.z"]
        ts, v = _read(reader, imu, fields, damage)
        for j, col in enumerate(("ax", "ay", "az", "gx", "gy", "gz")):
            aux[col] = align(t, ts, v[:, j])
        q = v[:, 6:10]
        good = np.abs(np.linalg.norm(q, axis=1) - 1) < 0.01    # ROS: an all-zero orientation means "none"
        if np.any(good):
            q = _qmul(Q_NED_ENU, q[good])
            q = align_quaternion(t, ts[good], q)
            for j, col in enumerate(("qw", "qx", "qy", "qz")):
                aux[col] = q[:, j]
    temp = _first_of(reader, TEMPERATURE)
    if temp:
        ts, v = _read(reader, temp, ["temperature"], damage)
        aux["temp"] = align(t, ts, v[:, 0])
    gps = _first_of(reader, NAVSATFIX)
    if gps:
        ts, v = _read(reader, gps, ["status.status", "latitude", "longitude", "altitude"], damage)
        fix = v[:, 0] >= 0                                  # STATUS_NO_FIX = -1
        aux["lat"] = align(t, ts[fix], v[fix, 1])
        aux["lon"] = align(t, ts[fix], v[fix, 2])
        aux["alt_wgs84"] = align(t, ts[fix], v[fix, 3])     # NavSatFix: above the ellipsoid, not sea level
    bat = _first_of(reader, BATTERY)
    if bat:
        ts, v = _read(reader, bat, ["current", "voltage"], damage)
        aux["current"] = align(t, ts, v[:, 0])
        aux["voltage"] = align(t, ts, v[:, 1])
    return aux


def _qmul(a, b):
    """Hamilton product a b of one quaternion a (4,) and rows b (n, 4), scalar first."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b.T
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)


def _choose(reader, path, instance, topic):
    mags = _candidates(reader)
    if topic is not None:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            raise FlightLogError(f"{path}: no topic {topic!r}; topics: {_topics_text(reader)}")
        if conns[0].msgtype not in (MAG_FIELD, VECTOR3):
            raise FlightLogError(f"{path}: topic {topic} is {conns[0].msgtype}, not a magnetometer "
                                 f"({MAG_FIELD} or {VECTOR3})")
        return topic, conns
    if not mags:
        raise FlightLogError(f"{path}: no magnetometer topic ({MAG_FIELD}, or {VECTOR3} named *mag*); "
                             f"topics: {_topics_text(reader)}")
    k = 0 if instance is None else int(instance)
    if not 0 <= k < len(mags):
        raise FlightLogError(f"{path}: no magnetometer instance {k}; instances: "
                             f"{', '.join(f'{i}={m}' for i, m in enumerate(mags))}")
    return mags[k], [c for c in reader.connections if c.topic == mags[k]]


def _stream(reader, conns, damage):
    mtype = conns[0].msgtype
    if mtype == MAG_FIELD:
        t, v = _read(reader, conns, ["magnetic_field.x", "magnetic_field.y", "magnetic_field.z"], damage)
        return t, v * TESLA_TO_UT, "uT", "tesla (x1e6 -> uT)"
    t, v = _read(reader, conns, ["vector.x", "vector.y", "vector.z"], damage)
    return t, v, "raw", "unknown: geometry_msgs/Vector3Stamped carries no unit"


def read_rosbag(path, instance=None, topic=None):
    """One magnetometer topic of a ROS 1/2 bag as a :class:`~mkc_stream.io.recording.Recording`."""
    reader = _open(path)
    try:
        name, conns = _choose(reader, path, instance, topic)
        damage: list = []
        t, mag, unit, unit_note = _stream(reader, conns, damage)
        aux = _aux(reader, t, damage)
        _truncation(reader, len(t), damage)
        ros2 = bag_path(path).is_dir()
        meta = {"format": "ROS 2 bag" if ros2 else "ROS 1 bag", "source": str(path), "units.mag": unit,
                "mag.topic": name, "mag.msgtype": conns[0].msgtype, "mag.unit_in_log": unit_note,
                "mag.instance": _candidates(reader).index(name) if name in _candidates(reader) else "by topic",
                "calibration": "as published on the topic (the bag does not say whether it was calibrated)",
                "time_source": "log", "units.time": "s (header stamps)",
                "attitude": "sensor_msgs/Imu orientation, ENU -> NED" if "qw" in aux else "none"}
    finally:
        reader.close()
    return build_recording(path, t, mag, aux, meta, damage)


def inspect_rosbag(path) -> dict:
    reader = _open(path)
    try:
        out = []
        damage: list = []
        for k, name in enumerate(_candidates(reader)):
            conns = [c for c in reader.connections if c.topic == name]
            t, _, unit, _ = _stream(reader, conns, damage)
            out.append({"id": k, "topic": name, "samples": int(len(t)), "rate_hz": rate_of(t),
                        "duration_s": float(t[-1] - t[0]) if len(t) else 0.0, "units": unit,
                        "aux": sorted(_aux(reader, t[:2], damage)), "applied_calibration": None})
        fmt = "ROS 2 bag" if bag_path(path).is_dir() else "ROS 1 bag"
        return {"format": fmt, "instances": out, "topics": _topics_text(reader), "damage": [w for _, w in damage]}
    finally:
        reader.close()
