"""Live MAVLink links through pymavlink: any connection string it takes (``udpin:0.0.0.0:14550``,
``udp:``, ``udpout:host:port``, ``tcp:host:port``, a serial device ``/dev/ttyACM0`` with ``baud``).

One magnetometer stream is read: the IMU message kind given (``RAW_IMU``, ``SCALED_IMU``,
``SCALED_IMU2``, ``SCALED_IMU3``, ``HIGHRES_IMU``) or the first of them that arrives, from the
system and component that sent it first. Units and time are converted by the ``.tlog`` reader's
own functions (:mod:`.flightlogs.tlog`): milligauss x0.1 -> uT (HIGHRES_IMU gauss x100), the
message's acc/gyro/temp with each sample, ``t`` = the message's time since the autopilot's boot (s).
The field is as the autopilot sends it (ArduPilot sends its corrected field; its calibration is
not undone live: the metadata says so).

Aux on each sample, the latest value of: ``ATTITUDE``/``ATTITUDE_QUATERNION`` (``qw..qz`` body ->
NED), ``BATTERY_STATUS`` or else ``SYS_STATUS`` current (A) and ``SYS_STATUS`` voltage (V),
``GPS_RAW_INT`` with a 3D fix (``lat, lon, alt``). A value older than ``AUX_HOLD_S`` is NaN: a
held value never bridges a gap in its own stream. Opening waits for the magnetometer stream and
then ``warmup_s`` more, so the recording's columns hold every aux signal the link sends.

Rates: on each autopilot's first HEARTBEAT the source asks for the messages it needs with
``MAV_CMD_SET_MESSAGE_INTERVAL`` and the older ``REQUEST_DATA_STREAM`` (harmless where ignored),
and sends a ground-station HEARTBEAT every second.

Counts: frames pymavlink cannot decode (bad CRC, bad prefix, wrong length) are bad frames; frames
missing from a system/component's 8-bit sequence number are drops, except as many as bad frames
were seen since that sender's last good frame (lost to corruption, already counted bad); a
sequence that jumps back is a restart (``seq_resets``). A link that sends nothing, or no
magnetometer message, for ``silence_s`` seconds raises :class:`~.source.SourceLost` (after the
samples already read).
"""
from __future__ import annotations

import math
import time
from types import SimpleNamespace

from .counters import DecodeCounts, SeqTracker
from .sample import Sample
from .source import BaseSource, SourceError, SourceLost

MAG_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU")
AUX_MESSAGES = ("ATTITUDE", "ATTITUDE_QUATERNION", "SYS_STATUS", "BATTERY_STATUS", "GPS_RAW_INT")
#: requested rates (Hz) of the aux messages
AUX_RATES = {"ATTITUDE": 50.0, "SYS_STATUS": 5.0, "BATTERY_STATUS": 5.0, "GPS_RAW_INT": 5.0}
#: an aux value older than this (s, host clock) is not carried onto a sample
AUX_HOLD_S = 1.0
SILENCE_S = 5.0
WARMUP_S = 0.5
#: messages handled per read, so one read stays short
MAX_MESSAGES = 4000
MAX_BAD_REASONS = 5
MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, MAV_AUTOPILOT_PX4 = 6, 8, 12
MAV_CMD_SET_MESSAGE_INTERVAL = 511
#: REQUEST_DATA_STREAM ids: RAW_SENSORS (RAW_IMU, SCALED_IMU2/3), EXTENDED_STATUS (SYS_STATUS,
#: GPS_RAW_INT), EXTRA1 (ATTITUDE)
STREAM_RAW_SENSORS, STREAM_EXTENDED_STATUS, STREAM_EXTRA1 = 1, 2, 6


def _mavutil():
    try:
        from pymavlink import mavutil
    except ImportError:
        raise SourceError('a live MAVLink link needs pymavlink: pip install "mkc-stream[mavlink]"') from None
    return mavutil


def _is_file(conn: str) -> bool:
    import pathlib

    return pathlib.Path(conn).is_file() and not conn.startswith("/dev/")


class MAVLinkSource(BaseSource):
    def __init__(self, conn: str, message: str | None = None, rate_hz: float = 100.0, baud: int = 115200,
                 silence_s: float = SILENCE_S, warmup_s: float = WARMUP_S, clock=time.monotonic):
        if message is not None and message not in MAG_MESSAGES:
            raise SourceError(f"MAVLink message {message!r} is not a magnetometer message; choose one of "
                              f"{', '.join(MAG_MESSAGES)}")
        if not rate_hz > 0 or not silence_s > 0:
            raise SourceError("the MAVLink rate and silence timeout must be positive")
        if _is_file(conn):
            raise SourceError(f"{conn} is a file: read a telemetry log with replay/calibrate, not as a live link")
        super().__init__(f"mavlink:{conn}", None, "device", "uT")
        self.decoder = SimpleNamespace(counts=DecodeCounts(), bad_reasons=[])
        self.conn_str, self.message, self.rate_hz = conn, message, float(rate_hz)
        self.silence_s, self.warmup_s, self._clock = float(silence_s), float(warmup_s), clock
        self.meta.update({"protocol": "mavlink", "units.time": "s since the autopilot's boot",
                          "calibration": "as sent by the autopilot, not undone (ArduPilot sends its corrected "
                                         "field)"})
        mavutil = _mavutil()
        try:
            self._conn = mavutil.mavlink_connection(conn, baud=int(baud), source_system=255, source_component=190,
                                                    robust_parsing=True)
        except Exception as exc:  # noqa: BLE001 - pymavlink raises socket, serial and value errors
            raise SourceError(f"cannot open the MAVLink link {conn}: {exc}") from None
        self._mavlink = mavutil.mavlink
        self._seq: dict[tuple[int, int], SeqTracker] = {}
        self._bad_since: dict = {}            # bad frames since each sender's last good frame
        self._bad_pending = 0
        self._requested: set = set()
        self._stream: tuple[int, int, str] | None = None
        self._aux: dict[str, tuple[float, float]] = {}      # column -> (value, host time)
        self._aux_keys: dict[str, None] = {}
        self._battery_status = False
        self._held: list = []                 # (receive time, message dict, aux snapshot)
        self._seen: set[str] = set()           # message kinds heard
        self._lost: str | None = None
        self._next_heartbeat = 0.0
        self.requests_sent = 0
        self.held_at_close = 0
        now = clock()
        self._last_heard = self._last_sample = now
        try:
            self._open_stream(now)
        except BaseException:
            self.close()
            raise

    # -- opening -------------------------------------------------------------------------------
    def _open_stream(self, start):
        """Read until the magnetometer stream is known (or the silence timeout), then ``warmup_s``
        more so every aux signal the link sends is known before the first sample goes out."""
        while self._stream is None:
            self._pump(0.05)
            if self._clock() - self._last_heard > self.silence_s or self._clock() - start > 2 * self.silence_s:
                what = f"only {', '.join(sorted(self._seen))}" if self._seen else "nothing"
                raise SourceError(f"no magnetometer message ({self.message or ' / '.join(MAG_MESSAGES)}) on the "
                                  f"MAVLink link {self.conn_str} within {self.silence_s:g} s (heard {what})")
        sysid, compid, kind = self._stream
        self.meta.update({"mag.topic": kind, "mavlink.system": str(sysid), "mavlink.component": str(compid),
                          "mag.unit_in_log": "gauss (x100 -> uT)" if kind == "HIGHRES_IMU"
                          else "milligauss (x0.1 -> uT)"})
        end = self._clock() + self.warmup_s
        while self._clock() < end:
            self._pump(0.02)

    # -- reading -------------------------------------------------------------------------------
    def _pump(self, timeout) -> int:
        """Handle what has arrived (waiting up to ``timeout`` s for the first byte); messages handled."""
        n = self._drain()
        if not n and timeout:
            try:
                self._conn.select(timeout)
            except Exception:  # noqa: BLE001 - a closed descriptor: the next recv says why
                pass
            n = self._drain()
        now = self._clock()
        if n:
            self._last_heard = now
        self._keepalive(now)
        return n

    def _drain(self) -> int:
        n = 0
        conn = self._conn
        while n < MAX_MESSAGES:
            try:
                m = conn.recv_msg()
            except Exception as exc:  # noqa: BLE001 - a socket or port that failed
                mav_error = type(exc).__name__ == "MAVError"
                if mav_error:
                    self._bad(str(exc))
                    n += 1
                    continue
                raise SourceLost(f"MAVLink link {self.conn_str} failed ({exc})") from None
            if m is None:
                break
            n += 1
            self._handle(m)
        return n

    def _bad(self, reason):
        c = self.decoder.counts
        c.bad_frames += 1
        self._bad_pending += 1
        reasons = self.decoder.bad_reasons
        if len(reasons) < MAX_BAD_REASONS:
            reasons.append(f"MAVLink frame that does not decode: {reason[:80]}")

    def _handle(self, m):
        kind = m.get_type()
        if kind == "BAD_DATA":
            self._bad(str(getattr(m, "reason", "")))
            return
        c = self.decoder.counts
        sender = (m.get_srcSystem(), m.get_srcComponent())
        tracker = self._seq.get(sender)
        if tracker is None:
            tracker = self._seq[sender] = SeqTracker(256)
        missing = tracker.missing(m.get_seq())
        if missing is None:
            c.seq_resets += 1
        elif missing:
            damaged = min(missing, self._bad_pending)
            c.drops += missing - damaged
        self._bad_pending = 0
        self._seen.add(kind)
        if kind == "HEARTBEAT":
            self._on_heartbeat(m, sender)
        elif kind in MAG_MESSAGES:
            if self._stream is None and (self.message is None or kind == self.message):
                self._stream = (*sender, kind)
            if self._stream == (*sender, kind):
                c.frames += 1
                self._last_sample = self._clock()
                self._held.append((self._clock(), m.to_dict(), self._snapshot()))
                return
        elif kind in AUX_MESSAGES and (self._stream is None or sender[0] == self._stream[0]):
            self._take_aux(kind, m)
            return
        c.ignored += 1

    def _take_aux(self, kind, m):
        from .flightlogs._common import quat_from_euler
        from .flightlogs.tlog import battery_current_a, battery_voltage_v, gps_position

        now = self._clock()
        vals: dict[str, float] = {}
        if kind == "ATTITUDE":
            q = quat_from_euler([m.roll], [m.pitch], [m.yaw])[0]
            vals = dict(zip(("qw", "qx", "qy", "qz"), map(float, q)))
        elif kind == "ATTITUDE_QUATERNION":
            vals = dict(zip(("qw", "qx", "qy", "qz"), (float(m.q1), float(m.q2), float(m.q3), float(m.q4))))
        elif kind == "BATTERY_STATUS":
            self._battery_status = True
            vals = {"current": float(battery_current_a(m.current_battery))}
        elif kind == "SYS_STATUS":
            vals = {"voltage": float(battery_voltage_v(m.voltage_battery))}
            if not self._battery_status:
                vals["current"] = float(battery_current_a(m.current_battery))
        elif kind == "GPS_RAW_INT" and m.fix_type >= 3:
            vals = dict(zip(("lat", "lon", "alt"), map(float, gps_position(m.lat, m.lon, m.alt))))
        for k, v in vals.items():
            self._aux[k] = (v, now)
            self._aux_keys.setdefault(k)

    def _snapshot(self) -> dict:
        now = self._clock()
        out = {}
        for k, (v, at) in self._aux.items():
            out[k] = v if now - at <= AUX_HOLD_S else math.nan
        return out

    # -- requests --------------------------------------------------------------------------------
    def _on_heartbeat(self, m, sender):
        if m.type == MAV_TYPE_GCS or m.autopilot == MAV_AUTOPILOT_INVALID or sender in self._requested:
            return
        self._requested.add(sender)
        kinds = [self.message or ("HIGHRES_IMU" if m.autopilot == MAV_AUTOPILOT_PX4 else "RAW_IMU")]
        mav, ml = self._conn.mav, self._mavlink
        try:
            for kind, rate in [(kinds[0], self.rate_hz)] + list(AUX_RATES.items()):
                msg_id = getattr(ml, f"MAVLINK_MSG_ID_{kind}")
                mav.command_long_send(sender[0], sender[1], MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                      int(round(1e6 / rate)), 0, 0, 0, 0, 0)
                self.requests_sent += 1
            for stream, rate in ((STREAM_RAW_SENSORS, self.rate_hz), (STREAM_EXTRA1, AUX_RATES["ATTITUDE"]),
                                 (STREAM_EXTENDED_STATUS, AUX_RATES["SYS_STATUS"])):
                mav.request_data_stream_send(sender[0], sender[1], stream, int(min(round(rate), 65535)), 1)
                self.requests_sent += 1
        except OSError:
            pass                              # a link that cannot be written to still streams

    def _keepalive(self, now):
        if now < self._next_heartbeat:
            return
        self._next_heartbeat = now + 1.0
        try:
            self._conn.mav.heartbeat_send(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, 0)
        except Exception:  # noqa: BLE001 - udpin before any peer, a read-only port: nothing to tell
            pass

    # -- the source interface --------------------------------------------------------------------
    def read(self, timeout: float | None = 0.05) -> list:
        if self._lost is not None and not self._held:
            raise SourceLost(self._lost)
        if self._lost is None:
            try:
                self._pump(timeout or 0.0)
            except SourceLost as exc:
                self._lost = str(exc)
            now = self._clock()
            if self._lost is None and now - self._last_heard > self.silence_s:
                self._lost = f"the MAVLink link {self.conn_str} went silent (nothing for {self.silence_s:g} s)"
            elif self._lost is None and now - self._last_sample > self.silence_s:
                self._lost = (f"the MAVLink link {self.conn_str} sent no {self._stream[2]} for {self.silence_s:g} s "
                              "(other messages still arrive)")
        return self._account(self._release())

    def _release(self) -> list:
        held, self._held = self._held, []
        if not held:
            return []
        from .flightlogs.tlog import MG_TO_UT, imu_arrays

        kind = self._stream[2]
        t, _, mag_mg, aux = imu_arrays(kind, [(r, d) for r, d, _ in held])
        mag = (mag_mg * MG_TO_UT).tolist()
        tl = t.tolist()
        acc = list(zip(aux["ax"].tolist(), aux["ay"].tolist(), aux["az"].tolist()))
        gyro = list(zip(aux["gx"].tolist(), aux["gy"].tolist(), aux["gz"].tolist()))
        temp = aux["temp"].tolist() if "temp" in aux else [None] * len(held)
        keys = self._aux_keys
        out = []
        for i, (_, _, snap) in enumerate(held):
            extra = {k: snap.get(k, math.nan) for k in keys} if keys else None
            out.append(Sample(tl[i], tuple(mag[i]), acc[i], gyro[i], temp[i], aux=extra))
        return out

    def detail(self) -> dict:
        d = super().detail()
        d["rate_requests_sent"] = self.requests_sent
        d["held_at_close"] = self.held_at_close
        return d

    def close(self):
        self.held_at_close = len(self._held)
        conn, self._conn = getattr(self, "_conn", None), None
        if conn is not None:
            try:
                conn.close()
            except Exception:  # noqa: BLE001 - closing a vanished port may fail; it is closed either way
                pass
