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


#: Paced's default longest wait between two samples, in wall-clock seconds (after ``speed``)
MAX_STEP_S = 60.0


class Paced:
    """Wrap a source: ``speed=1`` real time, ``speed=k`` k times faster, ``speed=inf`` no waiting.

    The first sample is released at once; each next one when its time step from the previous
    sample, divided by ``speed``, has passed on ``clock``. A time that is not finite or goes
    backwards is released at once (and a backward step re-anchors the pacing there). A step longer
    than ``max_step_s`` wall seconds (a log with a pause of hours, a clock that jumped) is shortened
    to ``max_step_s``; ``long_steps`` counts those and ``skipped_s`` adds up the wall time not
    waited (both in ``detail()``). ``read(timeout)`` waits at most ``timeout`` seconds, so a
    caller stays responsive.
    """

    def __init__(self, source, speed: float = 1.0, clock=time.monotonic, sleep=time.sleep,
                 max_step_s: float | None = MAX_STEP_S):
        if not speed > 0:
            raise ValueError("speed must be > 0")
        if max_step_s is not None and not max_step_s >= 0:
            raise ValueError("max_step_s must be >= 0")
        self.source, self.speed = source, float(speed)
        self.clock, self.sleep = clock, sleep
        self.max_step_s = max_step_s
        self.long_steps = 0
        self.skipped_s = 0.0
        self._buf: deque = deque()
        self._last_t: float | None = None        # time of the last finite sample scheduled
        self._last_due: float | None = None      # its wall-clock release time
        self._head_due: float | None = None      # release time of self._buf[0], once computed

    def __getattr__(self, name):            # url, meta, counts(), live ... of the source
        return getattr(self.source, name)

    @property
    def eof(self) -> bool:
        return self.source.eof and not self._buf

    def detail(self) -> dict:
        d = dict(self.source.detail())
        d["paced_long_steps"] = self.long_steps
        d["paced_skipped_s"] = self.skipped_s
        return d

    def _head(self, now: float) -> float:
        """Release time of the first buffered sample (computed once per sample, in order)."""
        if self._head_due is None:
            t = self._buf[0].t
            if self._last_due is None:
                self._last_due = now
            due = self._last_due
            if math.isfinite(t):
                if self._last_t is not None:
                    step = max(0.0, (t - self._last_t) / self.speed)
                    if self.max_step_s is not None and step > self.max_step_s:
                        self.long_steps += 1
                        self.skipped_s += step - self.max_step_s
                        step = self.max_step_s
                    due = self._last_due + step
                self._last_t, self._last_due = t, due
            self._head_due = due
        return self._head_due

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
        due = self._head(now)
        if due > now:
            wait = due - now if timeout is None else min(due - now, timeout)
            self.sleep(wait)
            now = self.clock()
        out = []
        buf = self._buf
        while buf and self._head(now) <= now:
            out.append(buf.popleft())
            self._head_due = None
            if not buf and not self.source.eof:
                buf.extend(self.source.read(0))
        return out

    def close(self):
        self.source.close()
