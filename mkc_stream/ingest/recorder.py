"""Write a recording CSV incrementally, as samples arrive, so a crash loses at most a second.

The file is the recording format of docs/spec/recording.md (read back by ``read_recording``): the
``# key: value`` metadata, the header, then one row per sample with floats written by ``repr``
(bit-exact round trip). Rows go straight to the final file (no temporary name: the point is that
what was received is on disk); every ``flush_s`` seconds the file is flushed and fsync'ed. A
``.gz`` name writes gzip with a sync flush, which ``read_recording`` reads up to the last flush
(it marks the last row of an unfinished gzip stream as truncated, so for a live recording that
may be cut, plain ``.csv`` keeps one row more).

Columns are fixed when the header is written (given, or from the fields of the first batch); a
later sample with a field the header lacks is counted in :attr:`unrecorded`, never dropped silently.
"""
from __future__ import annotations

import gzip
import math
import os
import pathlib
import time
import zlib
from collections import Counter

from ..recording_rules import REQUIRED
from .sample import columns_for, missing_fields, row_values


def _fmt(v) -> str:
    if isinstance(v, int):
        return str(v)
    v = float(v)                     # numpy scalars too: their repr is not a plain number
    if math.isnan(v):
        return "nan"
    s = repr(v)
    return s[:-2] if s.endswith(".0") else s


def _meta_line(key, value) -> str:
    key = str(key).replace(":", "_").replace("\n", " ").strip().lstrip("#") or "note"
    value = " ".join(str(value).splitlines())
    return f"# {key}: {value}".rstrip() + "\n"


class RecordingWriter:
    def __init__(self, path, meta=None, columns=None, flush_s: float = 1.0, clock=time.monotonic):
        self.path = pathlib.Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._raw = open(self.path, "wb")
        self._gz = self.path.name.lower().endswith(".gz")
        self._fh = gzip.GzipFile(filename="", mode="wb", fileobj=self._raw, mtime=0) if self._gz else self._raw
        self.meta = dict(meta or {})
        self.columns: list[str] | None = list(columns) if columns else None
        self.rows = 0
        self.unrecorded: Counter = Counter()
        self.flush_s, self.clock = float(flush_s), clock
        self._last_flush = clock()
        self._closed = False
        if self.columns:
            self._header()

    def _header(self):
        head = "".join(_meta_line(k, v) for k, v in self.meta.items()) + ",".join(self.columns) + "\n"
        self._fh.write(head.encode())
        cols = set(self.columns)
        self._has = (cols >= {"ax", "ay", "az"}, cols >= {"gx", "gy", "gz"}, "temp" in cols, "seq" in cols)

    def write(self, samples):
        if samples:
            if self.columns is None:
                self.columns = columns_for(samples)
                self._header()
            cols = self.columns
            has_acc, has_gyro, has_temp, has_seq = self._has
            lines = []
            for s in samples:
                lines.append(",".join(map(_fmt, row_values(s, cols))))
                if ((s.acc is not None and not has_acc) or (s.gyro is not None and not has_gyro)
                        or (s.temp is not None and not has_temp) or (s.seq is not None and not has_seq) or s.aux):
                    for f in missing_fields(s, cols):
                        self.unrecorded[f] += 1
            self._fh.write(("\n".join(lines) + "\n").encode())
            self.rows += len(samples)
        self.tick()

    def tick(self):
        """Flush if the last flush is ``flush_s`` old (call it even when no samples come)."""
        if self.clock() - self._last_flush >= self.flush_s:
            self.flush()

    def flush(self):
        if self._closed:
            return
        if self._gz:
            self._fh.flush(zlib.Z_SYNC_FLUSH)
        self._raw.flush()
        os.fsync(self._raw.fileno())
        self._last_flush = self.clock()

    def close(self):
        if self._closed:
            return
        if self.columns is None:
            self.columns = list(REQUIRED)
            self._header()
        if self._gz:
            self._fh.close()
        self._raw.flush()
        os.fsync(self._raw.fileno())
        self._raw.close()
        self._closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
