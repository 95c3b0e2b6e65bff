"""``open_source(url)``: one call for every kind of source, in the spirit of ``serial_for_url``.

* a recording (``.csv``, ``.csv.gz``) -> :class:`~.logs.RecordingSource`
* a flight log (PX4 ``.ulg``/``.px4log``, ArduPilot ``.bin``, MAVLink ``.tlog``, ROS bags;
  :mod:`.flightlogs`, extra ``logs``; ``LOG#instance=ID`` or ``BAG#topic=NAME`` chooses the
  stream) -> its Recording, replayed by :class:`~.logs.RecordingSource`
* a python-can log (``.log``, ``.asc``, ``.blf``, ``.trc``, ``.mf4``, python-can ``.csv``)
  -> :class:`~.logs.CanLogSource` (``can_id`` or ``dbc`` + ``mapping`` choose the decoder)
* ``can://INTERFACE/CHANNEL[?bitrate=N&can_id=0x110]`` (e.g. ``can://socketcan/can0``,
  ``can://virtual/test``, ``can://slcan//dev/ttyACM0``) -> :class:`~.can_source.CanBusSource`
* ``mavlink:CONN`` with any pymavlink connection string (``mavlink:udpin:0.0.0.0:14550``,
  ``mavlink:tcp:127.0.0.1:5760``, ``mavlink:/dev/ttyACM0``; keyword arguments ``message``,
  ``rate_hz``, ``silence_s``) -> :class:`~.mavlink_source.MAVLinkSource` (extra ``mavlink``)
* anything else is a serial port: a device path (``/dev/ttyUSB0``, ``COM3``), optionally
  prefixed ``serial:``, or a pyserial URL (``loop://``, ``socket://host:port``, ``rfc2217://``)
  -> :class:`~.serial_source.SerialSource` (``protocol`` required).
"""
from __future__ import annotations

import pathlib
import urllib.parse

from .canframe import DEFAULT_CAN_ID
from .source import SourceError

PYSERIAL_SCHEMES = ("loop", "socket", "rfc2217", "spy", "alt", "hwgrep", "cp2110")


def can_decoder(can_id=None, dbc=None, mapping=None, host_time=False):
    """The built-in frame layout, or a DBC mapping when ``dbc`` is given."""
    if dbc is not None:
        from .dbc import DbcDecoder, MappingError

        if not mapping:
            raise SourceError("--dbc needs --map COLUMN=[MESSAGE.]SIGNAL,... for at least mx, my, mz")
        try:
            return DbcDecoder(dbc, mapping, host_time=host_time)
        except MappingError as exc:
            raise SourceError(str(exc)) from None
    if mapping:
        raise SourceError("--map needs --dbc FILE")
    from .candecoder import MagFrameDecoder

    return MagFrameDecoder(DEFAULT_CAN_ID if can_id is None else can_id, host_time=host_time)


def _looks_like_file(url: str) -> bool:
    from .flightlogs import is_flight_log
    from .logs import CAN_LOG_SUFFIXES, _suffix

    return _suffix(pathlib.Path(url)) in CAN_LOG_SUFFIXES + (".csv",) or is_flight_log(url)


def open_source(url, *, protocol=None, baud=115200, can_id=None, dbc=None, mapping=None,
                reconnect=False, columns=None, raw_out=None, notify=None, **bus_kwargs):
    """Open ``url`` as a source (see the module documentation). Raises :class:`SourceError`."""
    url = str(url)
    scheme = url.split("://", 1)[0].lower() if "://" in url else ""
    if scheme == "can":
        return _open_can_url(url, can_id, dbc, mapping, raw_out, bus_kwargs)
    if url.lower().startswith("mavlink:"):
        from .mavlink_source import MAVLinkSource

        conn = url[len("mavlink:"):]
        conn = conn[2:] if conn.startswith("//") else conn
        return MAVLinkSource(conn, baud=baud, **bus_kwargs)
    if not scheme and (pathlib.Path(url).is_file() or _looks_like_file(url)):
        return open_log(url, can_id=can_id, dbc=dbc, mapping=mapping)
    if protocol is None:
        raise SourceError(f"{url} is not a recording or a CAN log, so it is read as a serial port; "
                          f"a serial port needs --protocol")
    from .serial_source import SerialSource

    port = url
    for prefix in ("serial://", "serial:"):
        if url.startswith(prefix):
            port = url[len(prefix):]
            break
    return SerialSource(port, protocol, baud=baud, reconnect=reconnect, columns=columns, notify=notify)


def open_log(path, *, can_id=None, dbc=None, mapping=None):
    """A recording, a flight log (:mod:`.flightlogs`: by suffix, and by content for .bin/.log) or a
    python-can log file, by its suffix (python-can's CSV by its header)."""
    from .flightlogs import is_flight_log, read_flight_log
    from .logs import CanLogSource, RecordingSource, is_can_log

    if is_flight_log(path):
        if dbc is not None or mapping:
            raise SourceError(f"{path} is a flight log; --dbc/--map apply to CAN logs only")
        from ..io.recording import RecordingError

        try:
            return RecordingSource(str(path), rec=read_flight_log(path))
        except (OSError, RecordingError) as exc:     # FlightLogError is a RecordingError
            raise SourceError(f"cannot read {path}: {exc}") from None
    path = pathlib.Path(path)
    if path.is_dir():
        raise SourceError(f"{path} is a directory, not a recording or a CAN log")
    if not path.exists():
        raise SourceError(f"no such file: {path}")
    if is_can_log(path):
        return CanLogSource(path, can_decoder(can_id, dbc, mapping, host_time=False))
    if dbc is not None or mapping:
        raise SourceError(f"{path} is a recording; --dbc/--map apply to CAN logs only")
    return RecordingSource(path)


def _open_can_url(url, can_id, dbc, mapping, raw_out, bus_kwargs):
    from .can_source import CanBusSource, open_bus

    parsed = urllib.parse.urlsplit(url)
    rest = url.split("://", 1)[1].split("?", 1)[0]
    interface, _, channel = rest.partition("/")
    from can.util import cast_from_string

    opts = {k: cast_from_string(v) for k, v in urllib.parse.parse_qsl(parsed.query)}
    if "can_id" in opts:
        v = opts.pop("can_id")
        can_id = v if isinstance(v, int) else int(str(v), 0)
    bitrate = int(opts.pop("bitrate")) if "bitrate" in opts else None
    decoder = can_decoder(can_id, dbc, mapping, host_time=True)
    bus = open_bus(interface or None, channel or None, bitrate, **opts, **bus_kwargs)
    return CanBusSource(bus, decoder, url=url, raw_out=raw_out)
