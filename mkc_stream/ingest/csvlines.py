"""Recording-format CSV lines over a byte stream (docs/spec/recording.md), header first.

``# key: value`` lines before the header become metadata; the header names the columns (``t``,
``mx``, ``my``, ``mz`` required); each following line is one sample with the device's ``t``.
Rows before any header, with the wrong number of cells, with a non-number, with a missing
required cell or with ``t`` going backwards are bad (the file reader's rules). A new header line
(the device restarted) starts over. A ``seq`` column, when present, counts drops (modulus from
``# seq_modulus``, default 65536).
"""
from __future__ import annotations

import math

from ..recording_rules import REQUIRED
from .counters import SeqTracker
from .decoder import BadFrame, LineDecoder, ascii_line
from .sample import ACC_COLUMNS, GYRO_COLUMNS, Sample


class CsvDecoder(LineDecoder):
    name = "csv"
    time_source = "device"

    def __init__(self, columns: list[str] | None = None):
        super().__init__()
        self.columns: list[str] | None = None
        self._seq = SeqTracker()
        self._bad_since_good = 0
        if columns is not None:
            self._set_header(list(columns))

    def _set_header(self, names: list[str]):
        if any(not n for n in names) or len(set(names)) != len(names):
            from ..io.recording import excerpt   # here: importing this module stays free of numpy

            raise BadFrame(f"header with empty or duplicate column names: {excerpt(','.join(names))}")
        self.columns = names
        ix = names.index
        self._ti, self._mi = ix("t"), [ix(c) for c in ("mx", "my", "mz")]
        self._ai = [ix(c) for c in ACC_COLUMNS] if set(ACC_COLUMNS) <= set(names) else None
        self._gi = [ix(c) for c in GYRO_COLUMNS] if set(GYRO_COLUMNS) <= set(names) else None
        self._tempi = ix("temp") if "temp" in names else None
        self._seqi = ix("seq") if "seq" in names else None
        used = set(REQUIRED) | {"temp", "seq"}
        used |= set(ACC_COLUMNS) if self._ai else set()
        used |= set(GYRO_COLUMNS) if self._gi else set()
        self._auxi = [(n, i) for i, n in enumerate(names) if n not in used]
        self._tmax = -math.inf
        self._seq = SeqTracker(int(float(self.meta.get("seq_modulus", 65536))))

    def parse_line(self, line: bytes, t_host: float) -> Sample | None:
        text = ascii_line(line).strip()
        if text.startswith("#"):
            body = text[1:].strip()
            key, sep, value = body.partition(":")
            if sep and key.strip():
                self.meta[key.strip()] = value.strip()
            return None
        cells = [c.strip() for c in text.split(",")]
        if set(REQUIRED) <= set(cells):
            self._set_header(cells)
            return None
        if self.columns is None:
            raise BadFrame("data row before the header row")
        if len(cells) != len(self.columns):
            raise BadFrame(f"cell count: expected {len(self.columns)} cells, got {len(cells)}")
        try:
            v = [float(c) if c else math.nan for c in cells]
        except ValueError:
            raise BadFrame("non-numeric cell") from None
        t, mag = v[self._ti], tuple(v[i] for i in self._mi)
        if not (math.isfinite(t) and all(math.isfinite(m) for m in mag)):
            raise BadFrame("missing or non-finite required cell (t, mx, my, mz)")
        if t < self._tmax:
            raise BadFrame(f"t decreasing: t={t!r} is below the earlier t={self._tmax!r}")
        self._tmax = t
        seq = None
        if self._seqi is not None and math.isfinite(v[self._seqi]):
            seq = int(v[self._seqi])
        return Sample(
            t, mag,
            tuple(v[i] for i in self._ai) if self._ai else None,
            tuple(v[i] for i in self._gi) if self._gi else None,
            None if self._tempi is None else v[self._tempi],
            seq, False,
            {n: v[i] for n, i in self._auxi} if self._auxi else None)

    def count_bad(self, reason: str, n: int = 1):
        super().count_bad(reason, n)
        self._bad_since_good += n

    def _line(self, line, t_host, out):
        n = len(out)
        super()._line(line, t_host, out)
        if len(out) > n and out[-1].seq is not None:
            # missing sequence numbers not explained by bad rows seen since the last good row are drops
            missing = self._seq.missing(out[-1].seq)
            if missing is None:
                self.counts.seq_resets += 1
            else:
                self.counts.drops += max(0, missing - self._bad_since_good)
            self._bad_since_good = 0


def encode_csv_header(columns, meta=None) -> bytes:
    lines = [f"# {k}: {v}" for k, v in (meta or {}).items()] + [",".join(columns)]
    return ("\n".join(lines) + "\n").encode()


def encode_csv_row(values) -> bytes:
    return (",".join(_fmt(v) for v in values) + "\n").encode()


def _fmt(v) -> str:
    if isinstance(v, int):
        return str(v)
    s = repr(float(v))
    return s[:-2] if s.endswith(".0") else s
