"""Read a live source on a background thread into a bounded queue, so a slow consumer never stalls
the port and a fast source never fills memory.

A serial port's kernel buffer holds a few kilobytes (a pty about 20 KB, a UART FIFO far less):
if the loop that feeds the calibrator, writes the recording and prints the status also had to
read the port, a long calibration step would overflow it. The reader thread only moves samples
into the queue; the numba kernels release the GIL, so both run at once.
"""
from __future__ import annotations

import threading
import time
from collections import deque

#: QueuedReader's bound: ~2 s of a 30 kHz source, ~30 MB of samples
QUEUE_CAPACITY = 65536
#: samples the loop takes per pass: at ~20-50k samples/s through the calibrator, well under 1 s
MAX_READ = 8192

_EOF = object()


class QueuedReader:
    """Read a live source on a background thread into a bounded queue (so a slow consumer never
    stalls the port, and a fast source never fills memory).

    Back-pressure: when a batch does not fit, the reader waits up to ``block_s`` for the loop to
    make room (a short stall of the loop costs nothing), then drops the batch and counts its
    samples in ``dropped`` (added to ``counts()["drops"]``). It does not wait longer: while it
    waits the port's own small kernel buffer overflows, and what is lost there is counted only
    by protocols with a sequence counter. Samples still queued when the reader is closed are
    counted in ``unprocessed_at_close``. Same interface as the source it wraps.
    """

    def __init__(self, source, capacity: int = QUEUE_CAPACITY, max_read: int = MAX_READ, poll_s: float = 0.05,
                 block_s: float = 0.05, clock=time.monotonic):
        if capacity < 1 or max_read < 1:
            raise ValueError("capacity and max_read must be >= 1")
        self.source = source
        self.capacity, self.max_read, self.block_s, self.clock = capacity, max_read, block_s, clock
        self.dropped = 0                 # samples dropped because the queue stayed full
        self.drop_events = 0             # batches dropped
        self.peak = 0                    # most samples ever queued
        self.unprocessed_at_close = 0
        self._buf: deque = deque()       # sample batches, then an exception and/or _EOF
        self._queued = 0
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(poll_s,), name="mkc-reader", daemon=True)
        self._thread.start()

    def __getattr__(self, name):            # url, meta, decoder, live ... of the source
        return getattr(self.source, name)

    # -- the reader thread -------------------------------------------------------------------
    def _run(self, poll_s):
        try:
            while not self._stop.is_set():
                batch = self.source.read(poll_s)
                if batch:
                    self._put(batch)
                if self.source.eof:
                    break
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            self._put_marker(exc)
        self._put_marker(_EOF)

    def _put(self, batch):
        n = len(batch)
        with self._cond:
            deadline = self.clock() + self.block_s
            while self._queued and self._queued + n > self.capacity and not self._stop.is_set():
                left = deadline - self.clock()
                if left <= 0:
                    break
                self._cond.wait(left)
            if self._queued and self._queued + n > self.capacity:
                self.dropped += n
                self.drop_events += 1
                return
            self._buf.append(batch)
            self._queued += n
            self.peak = max(self.peak, self._queued)
            self._cond.notify_all()

    def _put_marker(self, item):
        with self._cond:
            self._buf.append(item)
            self._cond.notify_all()

    # -- the consumer ------------------------------------------------------------------------
    @property
    def eof(self) -> bool:
        return self._done

    def read(self, timeout: float | None = 0.05) -> list:
        if self._error is not None:          # samples that came before the failure went out first
            exc, self._error = self._error, None
            raise exc
        out: list = []
        with self._cond:
            if not self._buf and not self._done:
                self._cond.wait(timeout)
            while self._buf and len(out) < self.max_read:
                item = self._buf[0]
                if item is _EOF:
                    self._done = True
                    break
                self._buf.popleft()
                if isinstance(item, BaseException):
                    if not out:
                        raise item
                    self._error = item
                    break
                self._queued -= len(item)
                out.extend(item)
            self._cond.notify_all()          # room for a waiting reader
        return out

    def counts(self, consumed: int | None = None) -> dict:
        c = dict(self.source.counts(consumed))
        c["drops"] += self.dropped
        return c

    def detail(self) -> dict:
        d = dict(self.source.detail())
        d.update({"queue_dropped": self.dropped, "queue_drop_events": self.drop_events,
                  "queue_capacity": self.capacity, "queue_peak": self.peak,
                  "unprocessed_at_close": self.unprocessed_at_close})
        return d

    def close(self):
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout=1.0)
        with self._cond:
            self.unprocessed_at_close = self._queued
        self.source.close()
