"""A device emulator: an IMU that streams at a real rate over a pty, a serial port or a CAN bus.

    python -m mkc_stream.ingest.emulator --protocol binary --rate 1000 --pty
    PTY /dev/pts/7                       <- first stdout line: the port to open
    python -m mkc_stream.ingest.emulator --protocol slcan --rate 500 --pty --link /tmp/ttyEMU

It is a separate process on purpose: the reader under test sees a real tty, real timing and
real back-pressure. Like a UART, it never blocks: when the reader does not read and the tty
buffer is full, frames are dropped (counted as overruns; the sequence counter still advances,
so the reader can count the drops). ``--protocol slcan`` behaves as a serial-CAN adapter: it
answers the slcan commands and streams the built-in CAN frame once the channel is opened
(``O``). ``--mavlink HOST:PORT`` sends MAVLink 2 over UDP instead (:func:`send_mavlink`).
``--drop-every N`` skips every N-th frame and ``--corrupt P`` flips bytes with
probability P, to test that a reader counts what it lost. The signal is a sensor sweeping the
sphere in a 50 uT field with hard and soft iron, gravity at a fixed angle to the field.
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time

import numpy as np

from .binary import IMU_F32, MAG_F32, MAG_I16, encode_frame
from .canframe import DEFAULT_CAN_ID, encode_mag_frame
from .csvlines import encode_csv_header, encode_csv_row
from .motioncal import encode_motioncal
from .vectornav import encode_vn

PROTOCOLS = ("binary", "binary-mag", "binary-i16", "motioncal", "motioncal-raw", "motioncal-uni",
             "csv", "vectornav", "vnimu", "slcan")
CSV_COLUMNS = ["t", "mx", "my", "mz", "ax", "ay", "az", "gx", "gy", "gz", "temp", "seq"]


class DeviceModel:
    """Deterministic synthetic IMU readings at sample index k (time k / rate)."""

    def __init__(self, seed: int = 0, rate: float = 100.0, field: float = 50.0, noise: float = 0.2,
                 sweep_s: float = 8.0):
        rng = np.random.default_rng(seed)
        self.rate, self.field, self.noise, self.sweep_s = float(rate), field, noise, float(sweep_s)
        self.hard_iron = rng.uniform(-30, 30, 3)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        lam = np.exp(rng.uniform(-0.15, 0.15, 3))
        lam /= np.prod(lam) ** (1 / 3)
        self.soft_iron = (q * lam) @ q.T                   # the S of m_cal = S (m_raw - b)
        self._inv_s = np.linalg.inv(self.soft_iron)
        dip = math.radians(60.0)                           # gravity at a fixed angle to the field
        self._g_rot = np.array([[1, 0, 0], [0, math.cos(dip), -math.sin(dip)], [0, math.sin(dip), math.cos(dip)]])
        self._rng = np.random.default_rng(seed + 1)

    def direction(self, t):
        z = np.cos(np.pi * t / self.sweep_s)               # pole to pole in sweep_s seconds
        phi = 2 * np.pi * t / (self.sweep_s / 7.3)         # about 7 turns on the way
        r = np.sqrt(np.clip(1 - z * z, 0, None))
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)

    def block(self, k0: int, n: int):
        """(t, mag uT, acc m/s^2, gyro rad/s, temp degC) for samples k0 .. k0+n-1."""
        t = (k0 + np.arange(n)) / self.rate
        u = self.direction(t)
        mag = (self.field * u) @ self._inv_s.T + self.hard_iron + self.noise * self._rng.normal(size=(n, 3))
        acc = 9.80665 * u @ self._g_rot.T + 0.02 * self._rng.normal(size=(n, 3))
        du = (self.direction(t + 1e-3) - u) / 1e-3
        gyro = np.cross(u, du)
        temp = 25.0 + 0.5 * np.sin(t / 30.0)
        return t, mag, acc, gyro, temp


def frame_encoder(protocol: str, can_id: int = DEFAULT_CAN_ID):
    """(k, t, mag, acc, gyro, temp) -> bytes for one sample, and the bytes sent once at start."""
    def tup(v):
        return tuple(float(x) for x in v)

    if protocol in ("binary", "binary-mag", "binary-i16"):
        ftype = {"binary": IMU_F32, "binary-mag": MAG_F32, "binary-i16": MAG_I16}[protocol]
        return (lambda k, t, m, a, g, tc: encode_frame(k, int(round(t * 1e6)), tup(m), tup(a), tup(g), float(tc),
                                                       ftype=ftype)), b""
    if protocol.startswith("motioncal"):
        kinds = {"motioncal": ("Raw", "Uni"), "motioncal-raw": ("Raw",), "motioncal-uni": ("Uni",)}[protocol]
        return (lambda k, t, m, a, g, tc: b"".join(encode_motioncal(tup(a), tup(g), tup(m), kd) for kd in kinds)), \
            b"Adafruit AHRS - IMU Calibration!\r\n"
    if protocol == "csv":
        return (lambda k, t, m, a, g, tc: encode_csv_row([float(t), *tup(m), *tup(a), *tup(g), float(tc), k])), \
            encode_csv_header(CSV_COLUMNS, {"sensor": "mkc emulator", "units.mag": "uT"})
    if protocol in ("vectornav", "vnimu"):
        kind, cs = ("VNYMR", "xor") if protocol == "vectornav" else ("VNIMU", "crc")
        return (lambda k, t, m, a, g, tc: encode_vn(kind, tup(m), tup(a), tup(g), float(tc), checksum=cs)), b""
    if protocol == "slcan":
        def slcan(k, t, m, a, g, tc):
            return f"t{can_id:03X}8{encode_mag_frame(tup(m), k).hex().upper()}\r".encode()
        return slcan, b""
    raise ValueError(f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")


class SlcanAdapter:
    """The command side of an slcan adapter: answers commands, knows whether the channel is open."""

    def __init__(self):
        self.open = False
        self._buf = bytearray()

    def handle(self, data: bytes) -> bytes:
        self._buf += data
        out = bytearray()
        while b"\r" in self._buf:
            i = self._buf.index(b"\r")
            cmd = bytes(self._buf[:i]).decode("ascii", "replace")
            del self._buf[:i + 1]
            if cmd in ("O", "L"):
                self.open = True
                out += b"\r"
            elif cmd == "C":
                self.open = False
                out += b"\r"
            elif cmd == "V":
                out += b"V1013\r"
            elif cmd == "N":
                out += b"NMKC1\r"
            elif cmd == "F":
                out += b"F00\r"
            elif cmd[:1] in ("S", "s", "Z", "Y", "M", "m") or cmd == "":
                out += b"\r"
            elif cmd[:1] == "t":
                out += b"z\r"
            elif cmd[:1] == "T":
                out += b"Z\r"
            else:
                out += b"\a"
        return bytes(out)


class Emulator:
    def __init__(self, protocol, rate, seed=0, count=None, duration=None, drop_every=0, corrupt=0.0,
                 can_id=DEFAULT_CAN_ID, sweep_s=8.0):
        self.protocol, self.rate = protocol, float(rate)
        self.model = DeviceModel(seed, rate, sweep_s=sweep_s)
        self.encode, self.banner = frame_encoder(protocol, can_id)
        self.count, self.duration = count, duration
        self.drop_every, self.corrupt = int(drop_every), float(corrupt)
        self._rng = np.random.default_rng(seed + 2)
        self.generated = self.written = self.overruns = self.dropped = self.corrupted_bytes = 0
        self.slcan = SlcanAdapter() if protocol == "slcan" else None
        self._block = None

    def _frame(self, k: int) -> bytes:
        B = 1024
        if self._block is None or not (self._block[0] <= k < self._block[0] + B):
            self._block = (k, *self.model.block(k, B))
        k0, t, m, a, g, tc = self._block
        j = k - k0
        data = self.encode(k, t[j], m[j], a[j], g[j], tc[j])
        if self.corrupt > 0:
            hit = self._rng.random(len(data)) < self.corrupt
            if hit.any():
                arr = bytearray(data)
                for i in np.flatnonzero(hit):
                    arr[i] ^= int(self._rng.integers(1, 256))
                self.corrupted_bytes += int(hit.sum())
                data = bytes(arr)
        return data

    def run(self, write, read=None):
        """Stream until count/duration. ``write(bytes) -> bytes written or None if the port is full``."""
        if self.banner:
            write(self.banner)
        start = time.monotonic()
        k = 0
        pending = b""
        while True:
            now = time.monotonic()
            if self.duration is not None and now - start >= self.duration:
                break
            if self.count is not None and k >= self.count:
                break
            if read is not None and self.slcan is not None:
                cmd = read()
                if cmd:
                    write(self.slcan.handle(cmd))
            due = int((now - start) * self.rate) + 1
            streaming = self.slcan is None or self.slcan.open
            while k < due and (self.count is None or k < self.count):
                if not streaming:           # a closed slcan channel forwards nothing; time still runs
                    k = due
                    break
                frame = self._frame(k)
                self.generated += 1
                k += 1
                if self.drop_every and k % self.drop_every == 0:
                    self.dropped += 1
                    continue
                if pending:                 # finish a frame the port took only part of
                    n = write(pending)
                    pending = pending[n or 0:]
                    if pending:
                        self.overruns += 1
                        continue
                n = write(frame)
                if n is None:
                    self.overruns += 1      # a full port: the frame is lost, as from a full UART FIFO
                else:
                    self.written += 1
                    pending = frame[n:]
            time.sleep(max(0.0, start + k / self.rate - time.monotonic()))

    def stats(self) -> str:
        return (f"emulator: {self.protocol} at {self.rate:g} Hz: generated {self.generated}, written "
                f"{self.written}, overruns {self.overruns} (port not read), dropped on purpose {self.dropped}, "
                f"corrupted bytes {self.corrupted_bytes}")


def _pty(link: str | None):
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)                       # no echo, no line editing: a byte pipe, like a UART
    os.set_blocking(master, False)
    name = os.ttyname(slave)
    if link:
        try:
            os.unlink(link)
        except FileNotFoundError:
            pass
        os.symlink(name, link)

    def write(data: bytes):
        try:
            return os.write(master, data)
        except BlockingIOError:
            return None

    def read():
        try:
            return os.read(master, 4096)
        except (BlockingIOError, OSError):
            return b""

    return name, write, read, (master, slave)


def run_can(bus, rate, count=None, duration=None, can_id=DEFAULT_CAN_ID, seed=0, stop=None, drop_every=0,
            sweep_s=8.0):
    """Send the built-in CAN frame at ``rate`` on a python-can bus (tests use the virtual bus)."""
    import can

    model = DeviceModel(seed, rate, sweep_s=sweep_s)
    start = time.monotonic()
    k = sent = 0
    block = None
    while (count is None or k < count) and (duration is None or time.monotonic() - start < duration):
        if stop is not None and stop.is_set():
            break
        due = int((time.monotonic() - start) * rate) + 1
        while k < due and (count is None or k < count):
            if block is None or k >= block[0] + 1024:
                block = (k, model.block(k, 1024)[1])
            mag = block[1][k - block[0]]
            k += 1
            if drop_every and k % drop_every == 0:
                continue
            bus.send(can.Message(arbitration_id=can_id, data=encode_mag_frame(mag, k - 1), is_extended_id=False))
            sent += 1
        time.sleep(max(0.0, start + k / rate - time.monotonic()))
    return sent


def send_mavlink(dest, mag_mg, rate=200.0, stop=None, corrupt_every=0, wait_s=10.0, linger_s=0.0, sysid=1,
                 compid=1):
    """An autopilot on a UDP link: RAW_IMU with ``mag_mg`` (n, 3) integer milligauss at ``rate`` Hz
    (time_usec = k x 1e6 / rate), ATTITUDE every 4th and SYS_STATUS every 20th sample, HEARTBEAT
    every second, each frame one datagram to ``dest`` (host, port), encoded by pymavlink. Every
    ``corrupt_every``-th RAW_IMU frame gets one payload byte flipped (its CRC then fails). Commands
    the reader sends back (rate requests) are collected. Ends after the last sample or when
    ``stop`` (a threading.Event) is set; returns what it did. First it sends HEARTBEATs until the
    reader answers (up to ``wait_s`` s; 0: start at once), so no sample goes to a port not yet open;
    after the last sample it goes on sending HEARTBEATs alone for ``linger_s`` s (a vehicle that
    stopped streaming its IMU)."""
    import socket

    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    stats = {"imu_sent": 0, "frames_sent": 0, "corrupted": [], "commands": [], "data_streams": [], "heard": 0}

    def send(msg, corrupt=False):
        buf = bytearray(msg.pack(mav))
        mav.seq = (mav.seq + 1) % 256
        if corrupt:
            buf[12] ^= 0x55               # a payload byte (the MAVLink 2 header is 10 bytes)
        sock.sendto(bytes(buf), dest)
        stats["frames_sent"] += 1

    def listen():
        while True:
            try:
                data = sock.recv(4096)
            except (BlockingIOError, OSError):
                return
            for m in parser.parse_buffer(data) or []:
                stats["heard"] += 1
                if m.get_type() == "COMMAND_LONG":
                    stats["commands"].append((m.command, int(m.param1), m.param2))
                elif m.get_type() == "REQUEST_DATA_STREAM":
                    stats["data_streams"].append((m.req_stream_id, m.req_message_rate))

    mag_mg = np.asarray(mag_mg).astype(int)
    period_us = int(round(1e6 / rate))
    give_up = time.monotonic() + wait_s
    while wait_s and not (stats["commands"] or stats["heard"]) and time.monotonic() < give_up:
        if stop is not None and stop.is_set():
            break
        send(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
        time.sleep(0.02)
        listen()
    start = time.monotonic()
    try:
        for k in range(mag_mg.shape[0]):
            if stop is not None and stop.is_set():
                break
            time.sleep(max(0.0, start + k / rate - time.monotonic()))
            listen()
            t_us = k * period_us
            if k % int(rate) == 0:
                send(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
            corrupt = bool(corrupt_every) and k % corrupt_every == corrupt_every - 1
            x, y, z = (int(v) for v in mag_mg[k])
            send(mav.raw_imu_encode(t_us, 0, 0, -1000, 0, 0, 0, x, y, z, 0, 2500), corrupt)
            stats["imu_sent"] += 1
            if corrupt:
                stats["corrupted"].append(k)
            if k % 4 == 0:
                send(mav.attitude_encode(t_us // 1000, 0.1, -0.2, 1.5, 0.0, 0.0, 0.0))
            if k % 20 == 0:
                send(mav.sys_status_encode(0, 0, 0, 0, 12000, 1234, -1, 0, 0, 0, 0, 0, 0))
        end = time.monotonic() + linger_s
        while time.monotonic() < end and not (stop is not None and stop.is_set()):
            send(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
            time.sleep(0.05)
        listen()
    finally:
        sock.close()
    return stats


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mkc_stream.ingest.emulator", description=__doc__.split("\n")[0])
    p.add_argument("--protocol", default="binary", choices=PROTOCOLS)
    p.add_argument("--rate", type=float, default=100.0, help="samples per second (default 100)")
    p.add_argument("--count", type=int, help="stop after N samples")
    p.add_argument("--duration", type=float, help="stop after S seconds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sweep-s", type=float, default=8.0, help="seconds for the sensor to sweep pole to pole")
    p.add_argument("--drop-every", type=int, default=0, help="skip every N-th frame (the counter still advances)")
    p.add_argument("--corrupt", type=float, default=0.0, help="flip each byte with this probability")
    p.add_argument("--can-id", type=lambda s: int(s, 0), default=DEFAULT_CAN_ID)
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--pty", action="store_true", help="create a pty pair and print 'PTY <path>' first")
    out.add_argument("--port", help="write to this serial port or pyserial URL")
    out.add_argument("--can-interface", help="send CAN frames on this python-can interface (with --can-channel)")
    out.add_argument("--mavlink", metavar="HOST:PORT", help="send MAVLink RAW_IMU (the sweep, in milligauss) over "
                                                           "UDP to HOST:PORT (e.g. a reader on udpin:0.0.0.0:14550)")
    p.add_argument("--link", help="--pty: also make this symlink to the pty (a stable name across restarts)")
    p.add_argument("--can-channel", help="the python-can channel for --can-interface")
    a = p.parse_args(argv)

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    cpu0, t0 = time.process_time(), time.monotonic()
    emu = Emulator(a.protocol, a.rate, a.seed, a.count, a.duration, a.drop_every, a.corrupt, a.can_id, a.sweep_s)
    try:
        if a.mavlink:
            host, _, port = a.mavlink.rpartition(":")
            n = a.count or int((a.duration or 60.0) * a.rate)
            mag = np.rint(10.0 * DeviceModel(a.seed, a.rate, sweep_s=a.sweep_s).block(0, n)[1])   # uT -> mG
            st = send_mavlink((host or "127.0.0.1", int(port)), mag, a.rate)
            print(f"emulator: sent {st['imu_sent']} RAW_IMU in {st['frames_sent']} MAVLink frames", file=sys.stderr)
            return 0
        if a.can_interface:
            import can

            with can.Bus(interface=a.can_interface, channel=a.can_channel) as bus:
                n = run_can(bus, a.rate, a.count, a.duration, a.can_id, a.seed, drop_every=a.drop_every,
                            sweep_s=a.sweep_s)
            print(f"emulator: sent {n} CAN frames", file=sys.stderr)
            return 0
        if a.pty:
            name, write, read, fds = _pty(a.link)
            print(f"PTY {name}", flush=True)
            emu.run(write, read)
        else:
            import serial

            port = serial.serial_for_url(a.port, baudrate=115200, timeout=0)
            emu.run(lambda d: port.write(d), lambda: port.read(4096))
    except KeyboardInterrupt:
        pass
    finally:
        wall = time.monotonic() - t0
        print(emu.stats() + f"; cpu {100 * (time.process_time() - cpu0) / max(wall, 1e-9):.1f}%",
              file=sys.stderr, flush=True)
        if a.link:
            try:
                os.unlink(a.link)
            except OSError:
                pass
    if a.pty:
        time.sleep(0.2)     # let the reader drain the last bytes before the pty closes
    return 0


if __name__ == "__main__":
    sys.exit(main())
