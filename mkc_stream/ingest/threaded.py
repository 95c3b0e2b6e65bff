"""Read a live source on a background thread, so a slow consumer never stalls the port.

A serial port's kernel buffer holds a few kilobytes (a pty about 20 KB, a UART FIFO far less):
if the loop that feeds the calibrator, writes the recording and prints the status also had to
read the port, a long calibration step would overflow it. The reader thread only moves
samples into a queue; the numba kernels release the GIL, so both run at once.
"""
from __future__ import annotations

import queue
import threading

_EOF = object()


class Threaded:
    def __init__(self, source, poll_s: float = 0.05):
        self.source = source
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._done = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(poll_s,), name="mkc-reader", daemon=True)
        self._thread.start()

    def __getattr__(self, name):
        return getattr(self.source, name)

    def _run(self, poll_s):
        try:
            while not self._stop.is_set():
                batch = self.source.read(poll_s)
                if batch:
                    self._q.put(batch)
                if self.source.eof:
                    break
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            self._q.put(exc)
        self._q.put(_EOF)

    @property
    def eof(self) -> bool:
        return self._done

    def read(self, timeout: float | None = 0.05) -> list:
        if self._error is not None:          # samples that came before the failure went out first
            exc, self._error = self._error, None
            raise exc
        out: list = []
        try:
            item = self._q.get(timeout=timeout)
            while True:
                if item is _EOF:
                    self._done = True
                    break
                if isinstance(item, BaseException):
                    if not out:
                        raise item
                    self._error = item
                    break
                out.extend(item)
                item = self._q.get_nowait()
        except queue.Empty:
            pass
        return out

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.source.close()
