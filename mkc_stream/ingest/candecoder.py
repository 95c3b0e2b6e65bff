"""Pure CAN message decoders: python-can Messages in, Samples out (no bus, no I/O).

``MagFrameDecoder`` reads the built-in layout (:mod:`.canframe`); ``DbcDecoder`` (in
:mod:`.dbc`) reads any layout through a DBC file. Both count frames of other ids as ignored and
take ``t`` from the message timestamp (the interface's receive time on a live bus, the logged
time in a log file). A frame stamped NaN, infinite or negative (a damaged log) is a bad frame,
never a sample: it would make phantom gaps and drops.
"""
from __future__ import annotations

import math
from collections import Counter

from .canframe import DEFAULT_CAN_ID, decode_mag_frame
from .counters import DecodeCounts, SeqTracker
from .decoder import SampleList
from .sample import Sample


class CanDecoder:
    """Base: counts, ids seen (for 'no frame with id ...' messages) and bad-frame reasons."""

    name = "can"
    units_mag = "uT"
    MAX_REASONS = 5

    def __init__(self, host_time: bool = False):
        self.counts = DecodeCounts()
        self.bad_reasons: list[str] = []
        self.ids_seen: Counter = Counter()
        self.host_time = host_time
        self.meta: dict[str, str] = {}
        self._bad_since_good = 0

    def count_bad(self, reason: str, explains_missing: bool = True):
        """One damaged frame; ``explains_missing``: it may be a frame that the sequence counter will
        show missing (a frame of another id cannot be)."""
        self.counts.bad_frames += 1
        if explains_missing:
            self._bad_since_good += 1
        if len(self.bad_reasons) < self.MAX_REASONS:
            self.bad_reasons.append(reason)

    def owns(self, msg) -> bool:
        """Whether ``msg`` has an id this decoder reads (else it is ignored)."""
        return True

    def _count_seq(self, tracker, seq: int):
        """Drops from the counter: missing numbers not explained by bad frames since the last good one
        (CAN frames are CRC-checked by the controller: what is missing was lost, unless it came damaged
        through a log or a serial adapter and was counted as bad already)."""
        missing = tracker.missing(seq)
        if missing is None:
            self.counts.seq_resets += 1
        else:
            self.counts.drops += max(0, missing - self._bad_since_good)
        self._bad_since_good = 0

    def feed(self, messages) -> list[Sample]:
        out = SampleList(self.counts)
        for msg in messages:
            if msg.is_error_frame:
                self.counts.ignored += 1
                continue
            t = msg.timestamp
            if not 0.0 <= t < math.inf:           # NaN fails too
                self.count_bad(f"id {msg.arbitration_id:#x}: time stamp {t!r} is not a finite time >= 0",
                               self.owns(msg))
                continue
            self.ids_seen[msg.arbitration_id] += 1
            s = self.decode(msg)
            if s is not None:
                out.append(s)
        return out

    def decode(self, msg) -> Sample | None:
        raise NotImplementedError

    def reset_stream(self):
        pass


class MagFrameDecoder(CanDecoder):
    name = "can-frame"

    def __init__(self, can_id: int = DEFAULT_CAN_ID, host_time: bool = False):
        super().__init__(host_time)
        self.can_id = int(can_id)
        self._seq = SeqTracker(1 << 16)
        self.meta = {"can_id": hex(self.can_id), "seq_modulus": "65536"}

    def owns(self, msg) -> bool:
        return msg.arbitration_id == self.can_id

    def decode(self, msg) -> Sample | None:
        if msg.arbitration_id != self.can_id:
            self.counts.ignored += 1
            return None
        if msg.is_remote_frame:
            self.count_bad("remote frame on the sample id")
            return None
        try:
            mag, seq = decode_mag_frame(msg.data[:msg.dlc] if msg.dlc < len(msg.data) else msg.data)
        except ValueError as exc:
            self.count_bad(f"id {self.can_id:#x}: {exc}")
            return None
        self.counts.frames += 1
        self._count_seq(self._seq, seq)
        return Sample(float(msg.timestamp), mag, seq=seq, host_time=self.host_time)

    def reset_stream(self):
        self._seq.reset()
