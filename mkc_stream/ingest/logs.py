"""File sources for replay: recording CSVs (spec/recording.md) and python-can log files.

``RecordingSource`` replays a recording through :func:`mkc_stream.io.recording.read_recording`
(bad rows counted with line numbers, gaps by the reader's rule, drops from a ``seq`` column).
``CanLogSource`` reads ``.log`` (candump), ``.asc``, ``.blf``, ``.trc``, python-can ``.csv`` and
``.mf4`` (asammdf, extra ``can-mf4``) with python-can's readers, through a CAN decoder. python-can's
readers stop at a damaged record; a candump ``.log`` (one frame per line, no state) is resumed
after the bad line, any other format ends there with the damage counted and reported.
"""
from __future__ import annotations

import gzip
import math
import pathlib

import numpy as np

from .counters import DecodeCounts
from .sample import ACC_COLUMNS, GYRO_COLUMNS, Sample
from .source import BaseSource, SourceError

BLOCK = 8192
CAN_LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".mf4", ".db")
MF4_NEEDS = 'reading .mf4 logs needs asammdf: pip install "mkc-stream[can-mf4]"'


def _suffix(path: pathlib.Path) -> str:
    s = [x.lower() for x in path.suffixes]
    return s[-2] if len(s) >= 2 and s[-1] == ".gz" else (s[-1] if s else "")


def is_pycan_csv(path: pathlib.Path) -> bool:
    """python-can's CSV log (header ``timestamp,arbitration_id,...``), not a recording."""
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.strip() and not line.lstrip().startswith("#"):
                    return line.strip().startswith("timestamp,arbitration_id")
    except OSError:
        return False
    return False


def is_can_log(path) -> bool:
    path = pathlib.Path(path)
    suf = _suffix(path)
    return suf in CAN_LOG_SUFFIXES or (suf == ".csv" and is_pycan_csv(path))


class RecordingSource(BaseSource):
    live = False

    def __init__(self, path):
        from ..io.recording import RecordingError, read_recording

        path = pathlib.Path(path)
        try:
            rec = read_recording(path)
        except (OSError, RecordingError) as exc:
            raise SourceError(f"cannot read {path}: {exc}") from None
        ts = rec.meta.get("time_source", "log")
        super().__init__(str(path), None, ts, rec.mag_unit)
        self.meta = dict(rec.meta, source=rec.meta.get("source", str(path)), time_source=ts)
        self.meta.setdefault("units.mag", rec.mag_unit)
        self.rec = rec
        self._host = ts == "host"
        self._pos = 0
        n = len(rec)
        self._gap_idx = rec.gap_indices()
        if self._host:                      # the live rule for host receive times (see GapCounter)
            dt = np.diff(rec.t)
            self._gap_idx = self._gap_idx[dt[self._gap_idx] > 0.1]
        # drops from a seq column: missing numbers between consecutive rows (backward jump = restart)
        self._drops_cum = np.zeros(n, dtype=np.int64)
        if "seq" in rec.aux and n > 1:
            mod = int(float(rec.meta.get("seq_modulus", 65536)))
            seq = rec.aux["seq"]
            ok = np.isfinite(seq[1:]) & np.isfinite(seq[:-1])
            miss = np.where(ok, np.mod(np.nan_to_num(seq[1:] - seq[:-1] - 1), mod), 0).astype(np.int64)
            miss[miss > mod // 2] = 0
            self._drops_cum[1:] = np.cumsum(miss)
        self._fields = self._columns(rec)

    @staticmethod
    def _columns(rec):
        a = rec.aux
        acc = [a[c] for c in ACC_COLUMNS] if all(c in a for c in ACC_COLUMNS) else None
        gyro = [a[c] for c in GYRO_COLUMNS] if all(c in a for c in GYRO_COLUMNS) else None
        used = set((ACC_COLUMNS if acc else ()) + (GYRO_COLUMNS if gyro else ()) + ("temp", "seq"))
        aux = {k: v for k, v in a.items() if k not in used}
        return acc, gyro, a.get("temp"), a.get("seq"), aux

    def read(self, timeout: float | None = 0.05) -> list[Sample]:
        a, b = self._pos, min(self._pos + BLOCK, len(self.rec))
        self._pos = b
        if b >= len(self.rec):
            self.eof = True
        if a == b:
            return []
        acc, gyro, temp, seq, aux = self._fields
        n = b - a
        t = self.rec.t[a:b].tolist()
        mag = list(zip(*(self.rec.mag[a:b, j].tolist() for j in range(3))))
        none = [None] * n
        accl = list(zip(*(c[a:b].tolist() for c in acc))) if acc else none
        gyrl = list(zip(*(c[a:b].tolist() for c in gyro))) if gyro else none
        tmpl = [None if math.isnan(v) else v for v in temp[a:b].tolist()] if temp is not None else none
        seql = [None if math.isnan(v) else int(v) for v in seq[a:b].tolist()] if seq is not None else none
        if aux:
            cols = {k: v[a:b].tolist() for k, v in aux.items()}
            auxl = [dict(zip(cols, vals)) for vals in zip(*cols.values())]
        else:
            auxl = none
        host = self._host
        out = [Sample(*row, host, x) for row, x in zip(zip(t, mag, accl, gyrl, tmpl, seql), auxl)]
        self.samples += n
        return out

    def counts(self, consumed: int | None = None) -> dict:
        k = self.samples if consumed is None else min(consumed, self.samples)
        # a bad row also leaves a hole in the counter: it is counted once, as bad, not as a drop
        missing = int(self._drops_cum[k - 1]) if k else 0
        return {"samples": k, "bad_frames": len(self.rec.bad_rows),
                "drops": max(0, missing - len(self.rec.bad_rows)),
                "gaps": int(np.count_nonzero(self._gap_idx < k - 1)) if k else 0}

    def detail(self) -> dict:
        d = DecodeCounts(frames=self.samples, bad_frames=len(self.rec.bad_rows)).as_dict()
        if self.rec.bad_rows:
            d["bad_reasons"] = [f"line {ln}: {why}" for ln, why in self.rec.bad_rows[:5]]
        return d


class CanLogSource(BaseSource):
    live = False

    def __init__(self, path, decoder):
        import can

        path = pathlib.Path(path)
        if not path.is_file():
            raise SourceError(f"no such CAN log: {path}")
        super().__init__(str(path), decoder, "log", decoder.units_mag)
        self.path = path
        self.stopped_early: str | None = None
        self._resumable = _suffix(path) == ".log"
        try:
            if self._resumable:
                self._fh = (gzip.open if path.name.lower().endswith(".gz") else open)(
                    path, "rt", encoding="utf-8", errors="replace")
                self._reader = can.io.CanutilsLogReader(self._fh)
            else:
                self._fh = None
                self._reader = can.LogReader(path)
        except NotImplementedError as exc:             # python-can's answer when asammdf is missing
            raise ImportError(MF4_NEEDS if _suffix(path) == ".mf4" else str(exc)) from None
        except Exception as exc:  # noqa: BLE001 - python-can raises format-specific errors
            raise SourceError(f"cannot read CAN log {path}: {exc}") from exc
        self._it = iter(self._reader)

    def read(self, timeout: float | None = 0.05) -> list[Sample]:
        import can

        msgs, out = [], []
        while len(msgs) < BLOCK and not self.eof:
            try:
                msgs.append(next(self._it))
            except StopIteration:
                self.eof = True
            except Exception as exc:  # noqa: BLE001 - a damaged record in the log
                out += self.decoder.feed(msgs)             # in order: the frames before the damage first
                msgs = []
                self.decoder.count_bad(f"damaged log record: {exc}")
                if self._resumable:
                    # a candump line has no state: a new reader goes on from the next line
                    self._it = iter(can.io.CanutilsLogReader(self._fh))
                else:
                    self.stopped_early = f"the log reader stopped at a damaged record ({exc})"
                    self.eof = True
        return self._account(out + self.decoder.feed(msgs))

    def detail(self) -> dict:
        d = super().detail()
        if self.stopped_early:
            d["stopped_early"] = self.stopped_early
        return d

    def close(self):
        for obj in (self._reader, self._fh):
            if obj is not None:
                try:
                    obj.stop() if hasattr(obj, "stop") else obj.close()
                except Exception:  # noqa: BLE001
                    pass
