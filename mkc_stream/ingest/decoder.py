"""Decoder base classes: pure, incremental byte decoders (``feed(bytes) -> samples``, no I/O).

Feeding the same bytes in any chunking gives the same samples and the same counts. The host
receive time ``t_host`` is passed in by the caller (a decoder never reads a clock) and is used
only for protocols whose frames carry no time.
"""
from __future__ import annotations

import math

from .counters import DecodeCounts
from .sample import Sample


class SampleList(list):
    """The samples of one feed, each with the decoder's (bad_frames, drops) as they stood once it
    was decoded (``after``). A decoder counts damage and drops before the good frame that follows
    them, so a run that stops inside a chunk counts what came before its last sample and nothing
    after it (:meth:`.source.Source.counts`)."""

    def __init__(self, counts: DecodeCounts):
        super().__init__()
        self._counts = counts
        self.after: list[tuple[int, int]] = []

    def append(self, sample):
        super().append(sample)
        self.after.append((self._counts.bad_frames, self._counts.drops))


class BadFrame(ValueError):
    """A frame or line that arrived damaged; the message says why."""


class Decoder:
    """Base: counters, the last few bad-frame reasons, and the common interface."""

    #: protocol name (``--protocol``)
    name = "?"
    #: where sample times come from: "device" (frames carry a clock) or "host" (receive time)
    time_source = "device"
    #: magnetometer unit of the samples
    units_mag = "uT"
    #: bad-frame reasons kept for the report (the first ones; all are counted)
    MAX_REASONS = 5

    def __init__(self):
        self.counts = DecodeCounts()
        self.bad_reasons: list[str] = []
        self.meta: dict[str, str] = {}

    def count_bad(self, reason: str, n: int = 1):
        self.counts.bad_frames += n
        if len(self.bad_reasons) < self.MAX_REASONS:
            self.bad_reasons.append(reason)

    def feed(self, data: bytes, t_host: float = math.nan) -> list[Sample]:
        raise NotImplementedError

    def flush(self) -> list[Sample]:
        """End of stream: decode what is left (a last line without its line ending)."""
        return []

    def reset_stream(self):
        """The byte stream was interrupted (port reopened): forget partial data, keep counts."""


class LineDecoder(Decoder):
    """Text protocols: one frame per line (``\\n`` or ``\\r\\n``).

    The first line may be the tail of a line sent before the port was opened: if it does not
    parse it is lead-in (counted, not bad). A line longer than ``MAX_LINE`` bytes is bad and is
    discarded up to its end, so a stream without line endings cannot grow the buffer.
    """

    MAX_LINE = 1024
    time_source = "host"

    def __init__(self):
        super().__init__()
        self._buf = bytearray()
        self._first = True
        self._overlong = False

    def parse_line(self, line: bytes, t_host: float) -> Sample | None:
        """A sample, None for a well-formed line of another kind; raise BadFrame if damaged."""
        raise NotImplementedError

    def feed(self, data: bytes, t_host: float = math.nan) -> list[Sample]:
        buf = self._buf
        buf += data
        out = SampleList(self.counts)
        start = 0
        while True:
            end = buf.find(b"\n", start)
            if end < 0:
                break
            line = bytes(buf[start:end])
            start = end + 1
            if self._overlong:           # the end of a line already reported as too long
                self._overlong = False
                self.counts.skipped_bytes += len(line) + 1
                continue
            if len(line) > self.MAX_LINE:
                self._too_long()
                self.counts.skipped_bytes += len(line) + 1
                continue
            self._line(line, t_host, out)
        del buf[:start]
        if len(buf) > self.MAX_LINE and not self._overlong:
            self._too_long()
            self._overlong = True
        if self._overlong:
            self.counts.skipped_bytes += len(buf)
            buf.clear()
        return out

    def _too_long(self):
        # judged the same whether the line arrived whole or in pieces (chunking never matters)
        self.count_bad(f"line longer than {self.MAX_LINE} bytes")
        self._first = False

    def _line(self, line: bytes, t_host: float, out: list):
        if line.endswith(b"\r"):
            line = line[:-1]
        if not line.strip():
            return
        first, self._first = self._first, False
        try:
            s = self.parse_line(line, t_host)
        except BadFrame as exc:
            if first:
                self.counts.lead_in_bytes += len(line)
            else:
                self.count_bad(str(exc))
            return
        if s is None:
            self.counts.ignored += 1
        else:
            self.counts.frames += 1
            out.append(s)

    def flush(self) -> list[Sample]:
        out = SampleList(self.counts)
        if self._buf and not self._overlong:
            self._line(bytes(self._buf), math.nan, out)
        self._buf.clear()
        self._overlong = False
        return out

    def reset_stream(self):
        self.counts.skipped_bytes += len(self._buf)
        self._buf.clear()
        self._first = True
        self._overlong = False


def ascii_line(line: bytes) -> str:
    """The line as text; a byte outside printable ASCII is damage."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        raise BadFrame("non-ASCII byte in a text line") from None
    if not text.isprintable():
        raise BadFrame("control character in a text line")
    return text


def parse_floats(cells: list[str], what: str) -> list[float]:
    try:
        vals = [float(c) for c in cells]
    except ValueError:
        raise BadFrame(f"{what}: a field is not a number") from None
    if not all(math.isfinite(v) for v in vals):
        raise BadFrame(f"{what}: a field is not finite")
    return vals
