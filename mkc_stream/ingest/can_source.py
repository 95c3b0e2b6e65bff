"""Live CAN buses through python-can: any interface and channel (socketcan, slcan, virtual ...).

Frames go to a pure CAN decoder (the built-in layout or a DBC mapping). Every received frame,
of any id, can also be written raw through a python-can writer (``can.Logger``: the format
follows the file suffix, ``.log`` candump, ``.asc``, ``.blf``, ``.trc``, ``.mf4``), flushed every
second. A bus error or a vanished adapter raises :class:`SourceLost`; a frame the interface
cannot parse (slcan over a noisy line) is a bad frame, not a crash.
"""
from __future__ import annotations

import time

from ..io.recording import excerpt
from .source import BaseSource, SourceError, SourceLost

MAX_BATCH = 1000


def open_bus(interface=None, channel=None, bitrate=None, **kwargs):
    """``can.Bus`` with python-can's own argument names; clear errors instead of tracebacks."""
    import can

    config = {k: v for k, v in dict(interface=interface, channel=channel, bitrate=bitrate).items() if v is not None}
    config.update(kwargs)
    try:
        return can.Bus(**config)
    except Exception as exc:  # noqa: BLE001 - python-can raises interface-specific errors
        raise SourceError(f"cannot open CAN bus {config}: {exc}") from exc


class CanBusSource(BaseSource):
    def __init__(self, bus, decoder, url: str | None = None, raw_out=None, owns_bus: bool = True):
        url = url or f"can://{getattr(bus, 'channel_info', 'bus')}"
        super().__init__(url, decoder, "host", decoder.units_mag)
        self.bus, self.owns_bus = bus, owns_bus
        self.raw_frames = 0
        self.raw_path = raw_out
        self._writer = None
        self._last_flush = time.monotonic()
        if raw_out is not None:
            import can

            try:
                self._writer = can.Logger(str(raw_out))
            except Exception as exc:  # noqa: BLE001
                raise SourceError(f"cannot write raw CAN frames to {raw_out}: {exc}") from exc
            self.meta["raw_frames"] = str(raw_out)

    def read(self, timeout: float | None = 0.05) -> list:
        import can

        msgs, out = [], []
        wait = timeout
        for _ in range(MAX_BATCH):
            try:
                msg = self.bus.recv(wait)
            except (ValueError, IndexError) as exc:
                # the interface could not parse what the adapter sent: one damaged frame
                out += self._decode(msgs)
                msgs = []
                self.decoder.count_bad(f"frame the interface could not parse: {excerpt(str(exc), 120, quote=False)}")
                continue
            except (can.CanError, OSError) as exc:
                self._flush(force=True)
                raise SourceLost(f"CAN bus {self.url} failed ({exc})") from exc
            if msg is None:
                break
            msgs.append(msg)
            wait = 0.0
        out += self._decode(msgs)
        self._flush()
        return self._account(out)

    def _decode(self, msgs) -> list:
        if self._writer is not None:
            for m in msgs:
                self._writer.on_message_received(m)
            self.raw_frames += len(msgs)
        return self.decoder.feed(msgs)

    def _flush(self, force=False):
        if self._writer is None:
            return
        now = time.monotonic()
        if force or now - self._last_flush >= 1.0:
            self._last_flush = now
            f = getattr(self._writer, "file", None)
            if f is not None and hasattr(f, "flush"):
                f.flush()

    def detail(self) -> dict:
        d = super().detail()
        d["raw_frames"] = self.raw_frames
        return d

    def close(self):
        if self._writer is not None:
            try:
                self._writer.stop()
            finally:
                self._writer = None
        if self.owns_bus and self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception:  # noqa: BLE001 - a vanished adapter cannot be told to close (slcan writes "C")
                pass
            finally:
                self.bus = None
