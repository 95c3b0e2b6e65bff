"""Serial ports (pyserial): device paths and every pyserial URL (``loop://``, ``socket://`` ...).

Bytes go to a pure decoder; samples without device time get the host receive time
(``time.time()``, Unix seconds). A port that disappears raises :class:`SourceLost`, or with
``reconnect=True`` is reopened every ``retry_s`` seconds until it comes back (the decoder forgets
the partial frame; the samples missed meanwhile show as a time gap).
"""
from __future__ import annotations

import struct
import time

from .protocols import make_decoder
from .source import BaseSource, SourceError, SourceLost


def _serial():
    import serial  # pyserial, a core dependency

    return serial


class SerialSource(BaseSource):
    def __init__(self, port: str, protocol: str, baud: int = 115200, reconnect: bool = False,
                 columns: list[str] | None = None, notify=None, retry_s: float = 0.5, clock=time.time):
        try:
            decoder = make_decoder(protocol, columns)
        except ValueError as exc:
            raise SourceError(str(exc)) from None
        super().__init__(port, decoder, decoder.time_source, decoder.units_mag)
        self.meta.update({"protocol": decoder.name, "baud": str(baud)})
        self.port, self.baud, self.reconnect = port, int(baud), reconnect
        self.notify = notify or (lambda msg: None)
        self.retry_s = retry_s
        self.reconnects = 0
        self._clock = clock
        self._timeout = 0.05
        self._next_try = 0.0
        self._failure: BaseException | None = None
        self._socket = port.lower().startswith("socket://")
        try:
            self._ser = self._open()
        except (OSError, ValueError) as exc:
            raise SourceError(f"cannot open serial port {port}: {exc}") from None

    def _open(self):
        return _serial().serial_for_url(self.port, baudrate=self.baud, timeout=self._timeout)

    def _waiting(self, ser) -> int:
        """Bytes ready to read. pyserial's socket in_waiting only says 0 or 1, and asking its read()
        for more than is there loses the bytes read when the peer closes: ask the socket itself."""
        if self._socket:
            try:
                import fcntl
                import termios

                return struct.unpack("i", fcntl.ioctl(ser.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]
            except (ImportError, OSError, AttributeError):
                pass
        return ser.in_waiting

    def read(self, timeout: float | None = 0.05) -> list:
        if self._failure is not None:            # the bytes read before the failure went out first
            exc, self._failure = self._failure, None
            self._lost(exc)
        ser = self._ser
        if ser is None:
            return self._retry(timeout)
        serial = _serial()
        data = b""
        try:
            if timeout != self._timeout:
                ser.timeout = self._timeout = timeout
            data = ser.read(self._waiting(ser) or 1)
            n = self._waiting(ser)
            if n:
                data += ser.read(n)
        except (serial.SerialException, OSError) as exc:
            if not data:
                self._lost(exc)
                return []
            self._failure = exc
        if not data:
            return []
        return self._account(self.decoder.feed(data, self._clock()))

    def _lost(self, exc):
        try:
            self._ser.close()
        except Exception:  # noqa: BLE001 - the port is gone; closing may fail too
            pass
        self._ser = None
        msg = f"serial port {self.port} disappeared ({exc})"
        if not self.reconnect:
            raise SourceLost(msg)
        self.notify(msg + "; reconnecting")
        self.decoder.reset_stream()

    def _retry(self, timeout) -> list:
        now = time.monotonic()
        if now < self._next_try:
            time.sleep(min(self._next_try - now, timeout or 0.05))
            return []
        self._next_try = now + self.retry_s
        try:
            self._ser = self._open()
        except (OSError, ValueError):
            return []
        self.reconnects += 1
        self.notify(f"serial port {self.port} is back (reconnect {self.reconnects})")
        return []

    def write(self, data: bytes) -> int:
        """Send bytes to the device (a start command, or pyserial's loop:// in examples)."""
        if self._ser is None:
            raise SourceLost(f"serial port {self.port} is not open")
        return self._ser.write(data)

    def detail(self) -> dict:
        d = super().detail()
        d["reconnects"] = self.reconnects
        return d

    def close(self):
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # noqa: BLE001 - closing a port that is gone may fail; it is closed either way
                pass
            finally:
                self._ser = None
