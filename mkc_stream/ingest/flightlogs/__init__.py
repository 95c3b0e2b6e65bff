"""Flight and robot logs as recordings: PX4 ULog, ArduPilot DataFlash, PX4 px4log, MAVLink
telemetry logs, ROS 1/2 bags.

``read_flight_log(path, instance=None, topic=None)`` returns the same
:class:`~mkc_stream.io.recording.Recording` a recording CSV gives (magnetometer in uT where the
log's unit is known; aux columns in m/s^2, rad/s, degC, A, V; ``qw..qz`` body -> NED; ``lat, lon,
alt``), one magnetometer instance at a time, with the metadata saying the format, the topic or
message, the instance, the unit in the log and whether the autopilot's calibration was undone.
``inspect_flight_log(path)`` lists the instances. The format is chosen by suffix (``.ulg``,
``.px4log``, ``.tlog``, ``.bag``, a ROS 2 bag folder or its ``.db3``/``.mcap``) and, for ``.bin``
and ``.log``, by the first bytes (DataFlash ``A3 95``, ULog ``ULog``; anything else, e.g. a
candump text ``.log``, is not a flight log). A path may end in ``#instance=ID`` or
``#topic=NAME``, which is how a command line chooses. The readers need the optional extras
``ulog``, ``mavlink``, ``ros`` (all three: ``logs``).
"""
from __future__ import annotations

from ._common import FlightLogError, sniff_format, split_selector

__all__ = ["FlightLogError", "inspect_flight_log", "is_flight_log", "read_flight_log", "sniff_format"]


def is_flight_log(path) -> bool:
    return sniff_format(path) is not None


def _reader(path):
    path, opts = split_selector(path)
    fmt = sniff_format(path)
    if fmt is None:
        raise FlightLogError(f"{path} is not a flight log this reader knows (.ulg, .bin, .px4log, .tlog, .bag, ROS 2 bag)")
    if not path.exists():
        raise FlightLogError(f"no such file: {path}")
    if path.is_file() and path.stat().st_size == 0:
        raise FlightLogError(f"{path}: the file is empty")
    if fmt == "ulog":
        from .ulog import inspect_ulog as inspect, read_ulog as read
    elif fmt in ("dataflash", "px4log"):
        from .dataflash import inspect_dataflash as inspect, read_dataflash as read
    elif fmt in ("rosbag1", "rosbag2"):
        from .rosbag import inspect_rosbag as inspect, read_rosbag as read
    else:
        from .tlog import inspect_tlog as inspect, read_tlog as read
    return path, opts, read, inspect


def read_flight_log(path, instance=None, topic=None):
    """One magnetometer stream of a flight log (see the module documentation)."""
    path, opts, read, _ = _reader(path)
    instance = opts.get("instance", instance)
    topic = opts.get("topic", topic)
    if instance is not None and not str(instance).lstrip("-").isdigit():
        raise FlightLogError(f"{path}: instance must be a whole number, got {instance!r}")
    return read(path, instance=None if instance is None else int(instance), topic=topic)


def inspect_flight_log(path) -> dict:
    """``{"format", "instances": [{"id", "samples", "rate_hz", "duration_s", "aux",
    "applied_calibration", ...}], "damage": [...]}`` of a flight log."""
    path, _, _, inspect = _reader(path)
    return inspect(path)
