"""The source protocol (what every live device, bus and file looks like) and its common base.

A source yields :class:`~.sample.Sample` batches from ``read(timeout)`` until ``eof``:

* ``read(timeout=0.05) -> list[Sample]``: what arrived; ``[]`` when nothing came within
  ``timeout`` seconds. Raises :class:`SourceLost` when a device or bus disappears.
* ``eof``: True once a file is exhausted (a device never ends by itself).
* ``meta``: recording metadata (``source``, ``units.mag``, ``time_source`` ...).
* ``counts()``: the spec's ``{"samples", "bad_frames", "drops", "gaps"}``; ``detail()``: every
  counter (resyncs, skipped bytes, ignored frames, reconnects ...).
* ``close()``; sources are context managers and iterate sample by sample.

Wrappers (:mod:`.pacing`, :mod:`.threaded`) have the same interface.
"""
from __future__ import annotations

import collections
import threading

from typing import Protocol, runtime_checkable

from ..recording_rules import HOST_TIME_MIN_GAP_S
from .counters import GapCounter
from .sample import Sample


class SourceError(Exception):
    """A source that cannot be opened (bad name, missing file, unknown protocol, missing extra)."""


class SourceLost(Exception):
    """A device or bus disappeared mid-run; the message says which and why."""


@runtime_checkable
class Source(Protocol):
    url: str
    meta: dict
    eof: bool

    def read(self, timeout: float | None = 0.05) -> list[Sample]: ...

    def counts(self, consumed: int | None = None) -> dict: ...

    def detail(self) -> dict: ...

    def close(self) -> None: ...


class BaseSource:
    """Shared bookkeeping: sample and gap counts, metadata, iteration, context manager."""

    #: a device or bus (True) or a file (False, may be paced)
    live = True

    def __init__(self, url: str, decoder=None, time_source: str = "device", units_mag: str = "uT"):
        self.url = url
        self.decoder = decoder
        self.eof = False
        self.samples = 0
        #: (k, bad frames, drops): the decoder's counts once sample k (1-based) was decoded, and
        #: so up to the next mark; a mark where they change, or one per chunk (at its first
        #: sample, the chunk's end counts) when the decoder gives no per-sample counts
        self._marks: collections.deque = collections.deque()
        self._marks_lock = threading.Lock()
        self.gaps = GapCounter(min_gap_s=HOST_TIME_MIN_GAP_S if time_source == "host" else 0.0)
        self.meta: dict[str, str] = {"source": url, "units.mag": units_mag, "time_source": time_source}
        if decoder is not None:
            self.meta.update(getattr(decoder, "meta", {}))

    def _account(self, samples: list[Sample]) -> list[Sample]:
        first = self.samples + 1
        self.samples += len(samples)
        upd = self.gaps.update
        for s in samples:
            upd(s.t)
        c = self.decoder.counts if self.decoder is not None else None
        if c is not None and samples:
            # what the decoder had counted when each sample came out: a run that stops at its N-th
            # sample while a reader thread decodes ahead counts the damage up to there, not the
            # damage the rest of that sample's chunk showed
            after = getattr(samples, "after", None)
            if after is None or len(after) != len(samples):
                after = [(c.bad_frames, c.drops)]
            with self._marks_lock:              # a reader thread appends while the run reads counts
                marks = self._marks
                for i, (b, d) in enumerate(after):
                    if not marks or marks[-1][1:] != (b, d):
                        marks.append((first + i, b, d))
        return samples

    def counts(self, consumed: int | None = None) -> dict:
        """The spec's counts; ``consumed``: samples a run actually used (it may stop mid-batch, and a
        reader thread may have decoded ahead: bad frames and drops are those the decoder had counted
        once the last consumed sample was decoded; by the end of its chunk for a decoder that gives
        no per-sample counts)."""
        c = self.decoder.counts if self.decoder is not None else None
        n = self.samples if consumed is None else consumed
        bad, drops = (c.bad_frames, c.drops) if c else (0, 0)
        with self._marks_lock:
            marks = self._marks
            while len(marks) > 1 and marks[1][0] <= n:      # marks before the one at sample n: done with
                marks.popleft()
            if c is not None and n < self.samples:
                bad, drops = marks[0][1:] if marks and marks[0][0] <= n else (0, 0)
        return {"samples": n, "bad_frames": bad, "drops": drops, "gaps": self.gaps.final()}

    def detail(self) -> dict:
        d = self.decoder.counts.as_dict() if self.decoder is not None else {}
        reasons = getattr(self.decoder, "bad_reasons", None)
        if reasons:
            d["bad_reasons"] = list(reasons)
        for extra in ("crc_errors", "unchecked", "time_resets"):
            if hasattr(self.decoder, extra):
                d[extra] = getattr(self.decoder, extra)
        return d

    def read(self, timeout: float | None = 0.05) -> list[Sample]:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __iter__(self):
        while not self.eof:
            yield from self.read()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
