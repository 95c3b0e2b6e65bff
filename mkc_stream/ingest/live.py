"""The loop behind ``live``, ``record`` and ``replay``: source -> recorder -> calibrator.

Samples are written to the recording as they arrive and handed to the calibrator in batches
(every ``feed_every_s`` seconds, or sooner when many are waiting): one ``update`` per batch
keeps the Python overhead per sample small. The loop ends at the end of a file, after
``max_samples`` samples or ``duration`` seconds (wall clock for a device, sample time for a
file), on Ctrl-C, or when the source is lost; in every case what was read is fed, recorded and
flushed before it returns.

Ctrl-C is a request, not an exception: on the main thread the loop takes SIGINT over and stops
at the top of its next pass (within one read timeout and one calibrator update), so the
interrupt never lands half-way through an update, a recorder write or a port close. A second
Ctrl-C raises KeyboardInterrupt as usual, for a loop that is stuck.

A device is read on its own thread by :class:`.threaded.QueuedReader` into a bounded queue: when the loop
cannot keep up (a 30 kHz source), the queue stops growing at ``capacity`` samples and what does
not fit is dropped and counted (``drops``), instead of memory growing without end and Ctrl-C
waiting for a backlog of minutes; each read hands the loop at most ``max_read`` samples, so one
pass (and so the answer to Ctrl-C) stays short.
"""
from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..jsonout import finite_or_none
from ..recording_rules import HOST_TIME_MIN_GAP_S
from .counters import GapCounter
from .source import SourceLost


@dataclass
class RunResult:
    samples: int
    ended: str                       # end of stream | max samples | duration | interrupted | source lost
    message: str | None
    elapsed_s: float
    cpu_s: float
    t_first: float | None
    t_last: float | None
    unfed: int = 0                   # recorded but not given to the calibrator (a stop cut the feed short)

    @property
    def cpu_percent(self) -> float | None:
        return 100.0 * self.cpu_s / self.elapsed_s if self.elapsed_s > 0 else None


class Run:
    def __init__(self, source, calibrator=None, recorder=None, *, max_samples=None, duration=None,
                 duration_in_sample_time=False, feed_every_s=0.05, max_batch=8192, feed_slice=1024, status=None,
                 status_every_s=0.25, read_timeout=0.05, clock=time.monotonic, cpu_clock=time.process_time):
        self.source, self.calibrator, self.recorder = source, calibrator, recorder
        self.max_samples = max_samples
        self.duration = duration
        self.sample_time = duration_in_sample_time
        self.feed_every_s, self.max_batch, self.feed_slice = feed_every_s, max_batch, feed_slice
        self.unfed = 0
        self.status, self.status_every_s = status, status_every_s
        self.read_timeout = read_timeout
        self.clock, self.cpu_clock = clock, cpu_clock
        self.samples = 0
        self.gaps = GapCounter()
        self.rate = 0.0
        self.last_event = None
        self.t_first: float | None = None
        self.t_last: float | None = None
        self._pending: list = []
        self.stop_requested = False

    def request_stop(self, *_):
        """Ask the loop to end at its next pass (the SIGINT handler; callable from any thread)."""
        self.stop_requested = True
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.default_int_handler)    # a second Ctrl-C interrupts

    # -- feeding ---------------------------------------------------------------------------
    def _feed(self):
        """Hand the pending samples to the calibrator, ``feed_slice`` at a time; after a stop request
        the rest is not fed (a slow calibrator would keep Ctrl-C waiting for seconds) but counted in
        ``unfed`` (those samples are recorded all the same)."""
        if self.calibrator is None or not self._pending:
            self._pending = []
            return
        mags = np.array([s.mag for s in self._pending], dtype=np.float64)
        self._pending = []
        for a in range(0, len(mags), self.feed_slice):
            if self.stop_requested:
                self.unfed += len(mags) - a
                break
            events = self.calibrator.learn_many(mags[a:a + self.feed_slice])
            if events:
                self.last_event = events[-1]

    def _take(self, batch) -> tuple[list, bool]:
        """Cut a batch at max_samples or at the sample-time duration; True when the run is complete."""
        done = False
        if self.max_samples is not None and self.samples + len(batch) >= self.max_samples:
            batch, done = batch[: self.max_samples - self.samples], True
        if self.duration is not None and self.sample_time and batch:
            t0 = self.t_first if self.t_first is not None else batch[0].t
            keep = [s for s in batch if not (s.t - t0 >= self.duration)]
            if len(keep) < len(batch):
                batch, done = keep, True
        return batch, done

    # -- the loop --------------------------------------------------------------------------
    def run(self) -> RunResult:
        start, cpu0 = self.clock(), self.cpu_clock()
        last_feed = last_status = start
        n_status = 0
        ended, message = "end of stream", None
        on_main = threading.current_thread() is threading.main_thread()
        if on_main:     # (getsignal may be None: a handler not set from Python; restored as-is)
            previous_handler = signal.signal(signal.SIGINT, self.request_stop)
        try:
            while True:
                if self.stop_requested:
                    ended = "interrupted"
                    break
                now = self.clock()
                if self.duration is not None and not self.sample_time and now - start >= self.duration:
                    ended = "duration"
                    break
                timeout = self.read_timeout
                if self.duration is not None and not self.sample_time:
                    timeout = max(0.0, min(timeout, self.duration - (now - start)))
                batch, done = self._take(self.source.read(timeout))
                if batch:
                    if self.t_first is None:
                        self.t_first = batch[0].t
                        if batch[0].host_time:
                            self.gaps = GapCounter(min_gap_s=HOST_TIME_MIN_GAP_S)
                    self.t_last = batch[-1].t
                    for s in batch:
                        self.gaps.update(s.t)
                    self.samples += len(batch)
                    if self.recorder is not None:
                        self.recorder.write(batch)
                    self._pending.extend(batch)
                elif self.recorder is not None:
                    self.recorder.tick()
                now = self.clock()
                if len(self._pending) >= self.max_batch or now - last_feed >= self.feed_every_s:
                    self._feed()
                    last_feed = self.clock()
                if self.status is not None and now - last_status >= self.status_every_s:
                    self.rate = (self.samples - n_status) / (now - last_status)
                    last_status, n_status = now, self.samples
                    self.status(self)
                if done:
                    ended = "max samples" if self.max_samples is not None and self.samples >= self.max_samples \
                        else "duration"
                    break
                if self.source.eof:
                    break
        except KeyboardInterrupt:
            ended = "interrupted"
        except SourceLost as exc:
            ended, message = "source lost", str(exc)
        finally:
            if on_main:
                signal.signal(signal.SIGINT, previous_handler if previous_handler is not None
                              else signal.default_int_handler)
            try:
                self._feed()
            finally:
                if self.recorder is not None:
                    self.recorder.close()
        elapsed = self.clock() - start
        return RunResult(self.samples, ended, message, elapsed, self.cpu_clock() - cpu0, self.t_first, self.t_last,
                         self.unfed)

    # -- what the status line and the report show ----------------------------------------
    def counts(self) -> dict:
        """The spec's counts for what this run consumed (a file's own gap rule when it has one)."""
        c = dict(self.source.counts(self.samples))
        if getattr(self.source, "live", True):
            c["gaps"] = self.gaps.final()
        c["samples"] = self.samples
        if self.calibrator is not None:
            c["bad_frames"] += self.calibrator.counts()["bad_frames"]   # non-finite samples
        return c

    @property
    def coverage(self) -> float | None:
        ev = self.last_event
        cov = None if ev is None else ev.coverage
        return finite_or_none(cov)
