"""What a decoder saw besides samples: bad frames, drops, resyncs, and the gap counter.

Counting rules (the same for every protocol, so reports compare):

* ``frames``: frames or lines that became samples.
* ``bad_frames``: frames that arrived damaged (CRC/checksum failure, unparsable line, wrong
  length) or, for protocols with a sequence counter, frames missing where bytes were discarded
  (lost to corruption).
* ``drops``: frames missing from the sequence counter with no damage seen (lost upstream:
  a full UART FIFO, a busy CAN controller).
* ``ignored``: well-formed frames of other kinds (other messages, banners, other CAN ids).
* ``resyncs`` / ``skipped_bytes``: times a byte decoder lost the frame boundary / bytes discarded.
* ``lead_in_bytes``: bytes before the first good frame (joining a stream mid-frame is normal).
* ``truncated``: an incomplete frame left when the stream ended.
* ``seq_resets``: the counter jumped backwards (device restart): neither a drop nor bad.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from ..recording_rules import GAP_FACTOR


@dataclass
class DecodeCounts:
    frames: int = 0
    bad_frames: int = 0
    drops: int = 0
    ignored: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    lead_in_bytes: int = 0
    truncated: int = 0
    seq_resets: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SeqTracker:
    """Frames missing between consecutive sequence numbers of a wrapping counter."""

    def __init__(self, modulus: int = 1 << 16):
        self.modulus = int(modulus)
        self.last: int | None = None

    def missing(self, seq: int) -> int | None:
        """Frames missing before ``seq``; None for the first frame or a backward jump (restart)."""
        last, self.last = self.last, int(seq) % self.modulus
        if last is None:
            return 0
        gap = (self.last - last - 1) % self.modulus
        # more than half the counter range "missing" is a counter that went backwards
        return None if gap > self.modulus // 2 else gap

    def reset(self):
        self.last = None


class GapCounter:
    """Streaming count of time gaps, the rule of the recording reader.

    A gap is a step larger than ``factor`` x the nominal period; the nominal period is the median
    of the first ``warmup`` positive steps (a file reader uses the median of all of them).
    ``min_gap_s``: with host receive times, samples arrive in bursts as the transport delivers
    them (a USB-serial adapter every few milliseconds), so shorter steps are jitter, not gaps.
    """

    def __init__(self, factor: float = GAP_FACTOR, warmup: int = 64, min_gap_s: float = 0.0):
        self.factor = float(factor)
        self.min_gap_s = float(min_gap_s)
        self.warmup = int(warmup)
        self.count = 0
        self.period: float | None = None
        self._last: float | None = None
        self._early: list[float] = []

    def update(self, t: float):
        last, self._last = self._last, t
        if last is None or not math.isfinite(t) or not math.isfinite(last):
            return
        dt = t - last
        if self.period is None:
            self._early.append(dt)
            pos = sorted(d for d in self._early if d > 0)
            if len(pos) >= self.warmup:
                self.period = pos[len(pos) // 2]
                limit = max(self.factor * self.period, self.min_gap_s)
                self.count += sum(d > limit for d in self._early)
                self._early = []
        elif dt > self.factor * self.period and dt > self.min_gap_s:
            self.count += 1

    def final(self) -> int:
        """Gaps so far; before the period is known, judged on the steps seen (as a file reader)."""
        if self.period is not None:
            return self.count
        pos = sorted(d for d in self._early if d > 0)
        if len(pos) < 2:
            return 0
        med = 0.5 * (pos[(len(pos) - 1) // 2] + pos[len(pos) // 2])
        return sum(d > max(self.factor * med, self.min_gap_s) for d in self._early)
