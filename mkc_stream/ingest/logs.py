"""File sources for replay: recording CSVs (docs/spec/recording.md) and python-can log files.

``RecordingSource`` replays a recording through :func:`mkc_stream.io.recording.read_recording`
(bad rows counted with line numbers, gaps by the reader's rule, drops from a ``seq`` column).
``CanLogSource`` reads ``.log`` (candump), ``.asc``, ``.blf``, ``.trc``, python-can ``.csv`` and
``.mf4`` (asammdf, extra ``can-mf4``) with python-can's readers, through a CAN decoder. python-can's
readers stop at a damaged record; a candump ``.log`` (one frame per line, no state) is resumed
after the bad line, any other format ends there with the damage counted and reported.

Nothing is lost silently: damage a reader passes over (a cut last record, which python-can drops
or half-reads; a line its TRC reader only logs; a BLF container it skips; what asammdf logs) is
counted as a bad frame, a cut file also as ``truncated`` with a warning (``stopped_early``), and an
ASC/TRC line that gave no frame as ``ignored``. A text log cut exactly at a line end cannot be told
from a whole one (an ASC log can: its trailer is missing). Text lines are bounded (MAX_LOG_LINE).
"""
from __future__ import annotations

import contextlib
import gc
import gzip
import logging
import math
import pathlib
import re
import struct
import sys
import zlib

import numpy as np

from ..io.recording import excerpt
from ..recording_rules import HOST_TIME_MIN_GAP_S
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
            for _ in range(1000):             # bounded: the first non-comment line within 1000 lines
                line = f.readline(4096)       # ... of at most 4096 characters (an endless input too)
                if not line:
                    break
                if line.strip() and not line.lstrip().startswith("#"):
                    return line.strip().startswith("timestamp,arbitration_id")
    except (OSError, EOFError, zlib.error):
        return False
    return False


def is_can_log(path) -> bool:
    path = pathlib.Path(path)
    suf = _suffix(path)
    return suf in CAN_LOG_SUFFIXES or (suf == ".csv" and is_pycan_csv(path))


class RecordingSource(BaseSource):
    live = False

    def __init__(self, path, rec=None):
        """``rec``: a Recording already read (a flight log's), replayed as it is."""
        from ..io.recording import RecordingError, read_recording

        path = pathlib.Path(path)
        try:
            rec = read_recording(path) if rec is None else rec
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
            self._gap_idx = self._gap_idx[dt[self._gap_idx] > HOST_TIME_MIN_GAP_S]
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


#: characters of one line of a text CAN log (python-can's lines are < 200); a longer line is
#: damage, skipped in bounded memory and counted
MAX_LOG_LINE = 4096
#: the first line of python-can's CSV log: column names only ("timestamp,arbitration_id,...,data";
#: another column set is still a header, a frame's values are not)
_CSV_HEADER_LINE = re.compile(r"[a-z_]+(,[a-z_]+)*")
#: the header lines python-can's ASC reader reads before the body (date, base, comments), and the
#: line that ends its header ("[no] internal events logged"; any other line ends it too, consumed)
_ASC_HEADER_LINE = re.compile(r"date\s+\w+\s+.+|base\s+(hex|dec)|//", re.IGNORECASE)
_ASC_EVENTS_LINE = re.compile(r"(no)?\s*internal\s+events\s+logged", re.IGNORECASE)
_TEXT_READERS = {".log": "CanutilsLogReader", ".asc": "ASCReader", ".trc": "TRCReader", ".csv": "CSVReader"}


class _TextLines:
    """The lines of a text CAN log, handed one by one to a python-can reader.

    Damage is noted in ``damage`` as ``(reason, kind)`` in file order, and the source counts each
    as a bad frame between the frames around it. ``kind`` is ``"bad"`` for a line longer than
    MAX_LOG_LINE (skipped), ``"cut"`` for a last line without its line ending (held back: every
    python-can writer ends each record with one, so the file was cut mid-record) or a gzip stream
    that ends early, and ``"stop"`` for a corrupt gzip stream (the lines end there). A python-can CSV
    log whose first line is not a header (column names only) is ``"bad"`` too (the reader skips that line
    unread, with any frame a damaged line ending joined to it). Universal
    newlines; undecodable bytes are replaced (the reader then refuses the line).
    """

    def __init__(self, path: pathlib.Path, damage: list, suffix: str = ".log"):
        gz = path.name.lower().endswith(".gz")
        self._fh = (gzip.open if gz else open)(path, "rt", encoding="utf-8", errors="replace")
        self.lineno = 0
        self.damage: list[tuple[str, str]] = damage
        self._kind = suffix
        self.asc_blocks = 0                   # "Begin Triggerblock" minus "End TriggerBlock"
        self.asc_header = suffix == ".asc"    # python-can's ASC reader is still reading the header
        # ASC and TRC: python-can skips a line it does not read as a frame (an event, an
        # unsupported type, or a damaged frame) without a word; a line of the body that gave no
        # frame is counted as ignored (the ASC reader reads every line after its header as a
        # possible frame, inside a trigger block or not: a "Begin Triggerblock" joined to the
        # header by a damaged line ending still leaves the frames read)
        self.pending = False                  # the last line handed out should give a frame
        self.skipped = 0
        self._ended = False

    def __iter__(self):
        return self

    def __next__(self) -> str:
        while not self._ended:
            try:
                line = self._fh.readline(MAX_LOG_LINE + 1)
                if len(line) > MAX_LOG_LINE and not line.endswith("\n"):
                    start = line
                    while line and not line.endswith("\n"):
                        line = self._fh.readline(MAX_LOG_LINE)
                    self.lineno += 1
                    self.damage.append((f"line {self.lineno}: longer than {MAX_LOG_LINE} characters "
                                        f"(it starts {excerpt(start[:40])}...)", "bad" if line else "cut"))
                    continue
            except EOFError:
                self._end("the gzip stream is truncated (it ends before its end marker)", "cut")
                break
            except (OSError, zlib.error) as exc:   # gzip.BadGzipFile is an OSError
                self._end(f"the gzip stream is corrupt ({excerpt(str(exc), 80, quote=False)})", "stop")
                break
            if not line:
                self._ended = True
                break
            self.lineno += 1
            if not line.endswith("\n"):
                if line.strip():
                    self._end(f"line {self.lineno}: the last line has no line ending (the file was cut "
                              f"mid-record): {excerpt(line.strip(), 60)}", "cut")
                break
            if self._kind == ".csv" and self.lineno == 1 and not _CSV_HEADER_LINE.fullmatch(line.strip()):
                # python-can's CSV reader drops its first line unread, as the header: a damaged line
                # ending can have joined the first frame to it
                self.damage.append((f"line 1: not python-can's CSV header (its reader skips the line, and "
                                    f"any frame in it): {excerpt(line.strip(), 80)}", "bad"))
            self._expect(line.strip().lower())
            return line
        self._expect("")
        raise StopIteration

    def _expect(self, low: str):
        """Count the previous line if it gave no frame; note whether this one should give one."""
        if self.pending:
            self.skipped += 1
        if self._kind == ".asc":
            if self.asc_header:
                # the reader's header loop: date, base and comment lines go on; the events line ends
                # it; any other line ends it too, consumed unread (a frame in it is lost: pending)
                if _ASC_HEADER_LINE.match(low):
                    self.pending = False
                    return
                self.asc_header = False
                if _ASC_EVENTS_LINE.match(low):
                    self.pending = False
                    return
            if low.startswith("begin triggerblock"):
                self.asc_blocks += 1
            elif low.startswith("end triggerblock"):
                self.asc_blocks -= 1
            self.pending = bool(low and not low.startswith(("//", "begin triggerblock", "end triggerblock"))
                                and not low.endswith("start of measurement"))
        elif self._kind == ".trc":
            self.pending = bool(low) and not low.startswith(";")

    def _end(self, reason: str, kind: str):
        self._ended = True
        self.damage.append((reason, kind))

    def close(self):
        self._fh.close()


class _ReaderLog(logging.Handler):
    """Damage that a reader only logs, then goes on without: python-can's TRC reader skips a line
    it cannot parse, its BLF reader a container it cannot unpack; asammdf drops what it cannot
    decode of an MF4 file (the amount is unknown).
    Here it becomes damage of the source (and is not printed)."""

    LOGGERS = {".trc": "can.io.trc", ".mf4": "asammdf", ".blf": "can.io.blf"}

    def __init__(self, suffix: str, damage: list, lines: _TextLines | None):
        super().__init__(logging.WARNING)
        self.suffix, self.damage, self.lines = suffix, damage, lines
        self.logger = logging.getLogger(self.LOGGERS[suffix])
        self.logger.addHandler(self)

    def emit(self, record):
        msg = record.getMessage().strip()
        if self.suffix == ".trc" and msg.startswith("TRCReader: Failed to parse"):
            self.damage.append((f"line {self.lines.lineno}: the TRC reader cannot parse it: "
                                f"{excerpt(msg, 100, quote=False)}", "bad"))
            self.lines.pending = False        # counted as bad, not as skipped
        elif self.suffix == ".blf":         # a container it cannot unpack, an object it cannot read
            self.damage.append((f"the BLF reader skips data: {excerpt(msg, 100, quote=False)}", "bad"))
        elif self.suffix == ".mf4" and record.levelno >= logging.ERROR:
            first = msg.splitlines()[0] if msg else ""
            self.damage.append((f"the MF4 reader (asammdf) reports damage and may have left out frames: "
                                f"{excerpt(first, 100, quote=False)}", "stop"))

    def remove(self):
        self.logger.removeHandler(self)


def _blf_damage(path: pathlib.Path) -> list[tuple[str, str]]:
    """Damage that python-can's BLF reader passes over silently, from the file's outer object
    headers, as ``(reason, kind)`` (see :class:`_TextLines`): a cut object (the reader drops it),
    an outer object that is not a container (skipped by the reader: a damaged type field), a file
    header size that does not fit. Damage of another kind is left to the reader, which raises."""
    from can.io.blf import FILE_HEADER_STRUCT, LOG_CONTAINER, OBJ_HEADER_BASE_STRUCT

    size = path.stat().st_size
    out = []
    with open(path, "rb") as f:
        head = f.read(FILE_HEADER_STRUCT.size)
        if len(head) < FILE_HEADER_STRUCT.size or head[:4] != b"LOGG":
            return out
        header = FILE_HEADER_STRUCT.unpack(head)
        pos, announced = header[1], header[10]
        if pos > size:
            return [(f"the file ends inside its header ({size} of {pos} bytes)", "cut")]
        if pos < FILE_HEADER_STRUCT.size:
            return [(f"the file header says it is {pos} bytes long", "stop")]
        while pos < size:
            f.seek(pos)
            base = f.read(OBJ_HEADER_BASE_STRUCT.size)
            if len(base) < OBJ_HEADER_BASE_STRUCT.size:
                return out + [(f"the file ends inside an object header (byte {pos} of {size})", "cut")]
            sig, _, _, obj_size, obj_type = OBJ_HEADER_BASE_STRUCT.unpack(base)
            if sig != b"LOBJ" or obj_size < OBJ_HEADER_BASE_STRUCT.size:
                return out
            if pos + obj_size > size:
                return out + [(f"the file ends inside an object (bytes {pos}-{pos + obj_size} of a "
                               f"{size}-byte file)", "cut")]
            if obj_type != LOG_CONTAINER:
                out.append((f"an outer object of type {obj_type} at byte {pos}, which the reader skips "
                            f"(a damaged container?)", "bad"))
            pos += obj_size + obj_size % 4
        if announced > pos:            # cut at an object boundary after the writer finished
            out.append((f"the file has {size} bytes, its header says {announced}", "cut"))
    return out


@contextlib.contextmanager
def _quiet_asammdf_del():
    """asammdf's MDF4.__del__ raises AttributeError for a file its constructor refused (a cut .mf4),
    which Python prints as a second traceback after the clear error; that one is dropped here."""
    hook = sys.unraisablehook

    def quiet(u):
        if getattr(u.object, "__qualname__", "") != "MDF4.__del__":
            hook(u)

    sys.unraisablehook = quiet
    try:
        yield
        gc.collect()
    finally:
        sys.unraisablehook = hook


class CanLogSource(BaseSource):
    live = False

    def __init__(self, path, decoder):
        import can

        path = pathlib.Path(path)
        if path.is_dir():
            raise SourceError(f"{path} is a directory, not a CAN log")
        if not path.exists():
            raise SourceError(f"no such CAN log: {path}")
        super().__init__(str(path), decoder, "log", decoder.units_mag)
        self.path = path
        self.stopped_early: str | None = None
        suffix = _suffix(path)
        self._suffix = suffix
        self._resumable = suffix == ".log"
        self._lines: _TextLines | None = None
        self._damage: list[tuple[str, str]] = []       # (reason, kind) in file order, see _TextLines
        self._log = None
        if path.is_file() and path.stat().st_size == 0:
            raise SourceError(f"{path}: the file is empty; not a CAN log")
        err = None
        with _quiet_asammdf_del():
            try:
                if suffix in _TEXT_READERS:
                    self._lines = _TextLines(path, self._damage, suffix)
                if suffix in _ReaderLog.LOGGERS:
                    self._log = _ReaderLog(suffix, self._damage, self._lines)
                if self._lines is not None:
                    self._reader = getattr(can.io, _TEXT_READERS[suffix])(self._lines)
                else:
                    self._reader = can.LogReader(path)
            except NotImplementedError as exc:             # python-can's answer when asammdf is missing
                if suffix == ".mf4":
                    raise ImportError(MF4_NEEDS) from None
                err = excerpt(str(exc), 200, quote=False)
            except Exception as exc:  # noqa: BLE001 - python-can raises format-specific errors
                err = excerpt(str(exc) or type(exc).__name__, 200, quote=False)
                if suffix == ".blf" and isinstance(exc, struct.error):   # python-can on a short header
                    err = f"not a BLF file: it ends inside the file header ({path.stat().st_size} bytes)"
                elif type(exc).__name__ == "BLFParseError":
                    err = "not a BLF file (no 'LOGG' signature)"
                elif suffix == ".mf4":
                    err += " (a cut or damaged MF4 file)"
        if err is not None:
            self.close()
            raise SourceError(f"cannot read CAN log {path}: {err}")
        self._blf_damage = _blf_damage(path) if suffix == ".blf" and not path.name.lower().endswith(".gz") else []
        self._it = iter(self._reader)

    def read(self, timeout: float | None = 0.05) -> list[Sample]:
        import can

        msgs, out = [], []
        lines, damage = self._lines, self._damage
        while len(msgs) < BLOCK and not self.eof:
            try:
                m = next(self._it)
            except StopIteration:
                self.eof = True
                out += self.decoder.feed(msgs)
                msgs = []
                self._count_damage()
                self._end_of_log()
            except Exception as exc:  # noqa: BLE001 - a damaged record in the log
                out += self.decoder.feed(msgs)             # in order: the frames before the damage first
                msgs = []
                self._count_damage()
                why = excerpt(str(exc) or type(exc).__name__, 120, quote=False)
                if not any(kind == "cut" for _, kind in self._blf_damage):   # else: the cut, counted below
                    self.decoder.count_bad(f"damaged log record: {why}")
                if self._resumable:
                    # a candump line has no state: a new reader goes on from the next line
                    self._it = iter(can.io.CanutilsLogReader(lines))
                else:
                    self._stopped(f"the log reader stopped at a damaged record "
                                  f"({why})")
                    self.eof = True
                    self._end_of_log()
            else:
                if damage:                                 # damage between the last frame and this one
                    out += self.decoder.feed(msgs)
                    msgs = []
                    self._count_damage()
                if lines is not None:
                    lines.pending = False
                msgs.append(m)
        return self._account(out + self.decoder.feed(msgs))

    def _count_damage(self):
        for reason, kind in self._damage:
            self.decoder.count_bad(f"damaged log record: {reason}")
            if kind == "cut":
                self._truncated(reason)
            elif kind == "stop":
                self._stopped(f"the log reader stopped: {reason}")
        self._damage.clear()

    def _truncated(self, reason: str):
        self.decoder.counts.truncated += 1
        self._stopped(f"the log is truncated: {reason}; the frames before the cut were read, "
                      f"the cut record is a bad frame")

    def _stopped(self, note: str):
        self.stopped_early = note if self.stopped_early is None else f"{self.stopped_early}; {note}"

    def _end_of_log(self):
        """Damage that only shows at the end: BLF objects, an ASC without its trailer."""
        if self._lines is not None and self._lines.skipped:
            self.decoder.counts.ignored += self._lines.skipped
            self._lines.skipped = 0
        if self._blf_damage:
            self._damage += self._blf_damage
            self._blf_damage = []
            self._count_damage()
        tail = getattr(self._reader, "_tail", b"")      # python-can's BLF reader: a partial object left
        if self._suffix == ".blf" and b"LOBJ" in tail and not self.decoder.counts.truncated:
            reason = f"the last object is incomplete ({len(tail)} bytes left over)"
            self.decoder.count_bad(f"damaged log record: {reason}")
            self._truncated(reason)
        if (self._lines is not None and self._lines.asc_blocks > 0 and not self.decoder.counts.truncated
                and self.stopped_early is None):
            reason = "the ASC log ends without 'End TriggerBlock' (the file was cut or not closed)"
            self.decoder.count_bad(f"damaged log record: {reason}")
            self._truncated(reason)

    def detail(self) -> dict:
        d = super().detail()
        if self.stopped_early:
            d["stopped_early"] = self.stopped_early
        return d

    def close(self):
        if self._log is not None:
            self._log.remove()
            self._log = None
        for obj in (getattr(self, "_reader", None), self._lines):
            if obj is not None:
                try:
                    obj.stop() if hasattr(obj, "stop") else obj.close()
                except Exception:  # noqa: BLE001
                    pass
