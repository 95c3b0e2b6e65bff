"""Pacing: release a file source's samples at the pace of their timestamps, or as fast as possible.

The clock and the sleep function are injected, so tests run a paced replay of minutes in
microseconds with a fake clock (python-can's ``MessageSync`` idea, for samples).
"""
from __future__ import annotations

import math
import time
from collections import deque


class FakeClock:
    """A clock that only moves when slept on: ``clock=fc.now``, ``sleep=fc.sleep``."""

    def __init__(self, t0: float = 0.0):
        self.t = float(t0)
        self.slept = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float):
        dt = max(0.0, float(dt))
        self.t += dt
        self.slept += dt


class Paced:
    """Wrap a source: ``speed=1`` real time, ``speed=k`` k times faster, ``speed=inf`` no waiting.

    The first sample is released at once; sample ``i`` when ``(t_i - t_0) / speed`` seconds
    have passed on ``clock``. A time that is not finite or goes backwards is released at once.
    ``read(timeout)`` waits at most ``timeout`` seconds, so a caller stays responsive.
    """

    def __init__(self, source, speed: float = 1.0, clock=time.monotonic, sleep=time.sleep):
        if not speed > 0:
            raise ValueError("speed must be > 0")
        self.source, self.speed = source, float(speed)
        self.clock, self.sleep = clock, sleep
        self._buf: deque = deque()
        self._start: float | None = None
        self._t0 = 0.0

    def __getattr__(self, name):            # url, meta, counts(), detail(), live ... of the source
        return getattr(self.source, name)

    @property
    def eof(self) -> bool:
        return self.source.eof and not self._buf

    def _due(self, t: float) -> float:
        if not math.isfinite(t):
            return -math.inf
        return self._start + (t - self._t0) / self.speed

    def read(self, timeout: float | None = 0.05) -> list:
        if math.isinf(self.speed):
            out = list(self._buf) + self.source.read(timeout)
            self._buf.clear()
            return out
        if not self._buf and not self.source.eof:
            self._buf.extend(self.source.read(timeout))
        if not self._buf:
            return []
        now = self.clock()
        if self._start is None:
            first = next((s.t for s in self._buf if math.isfinite(s.t)), 0.0)
            self._start, self._t0 = now, first
        due = self._due(self._buf[0].t)
        if due > now:
            wait = due - now if timeout is None else min(due - now, timeout)
            self.sleep(wait)
            now = self.clock()
        out = []
        buf = self._buf
        while buf and self._due(buf[0].t) <= now:
            out.append(buf.popleft())
            if not buf and not self.source.eof:
                buf.extend(self.source.read(0))
        return out

    def close(self):
        self.source.close()
