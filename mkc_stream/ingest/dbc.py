"""CAN frames of any layout, decoded through a DBC file and a signal-to-column mapping (cantools).

A mapping entry is ``COLUMN=[MESSAGE.]SIGNAL[*SCALE]``, e.g. ``mx=imu_mag.MagX*0.1``; several
may be given comma-separated. ``mx``, ``my`` and ``mz`` are required and must be signals of one
message, whose arrival emits a sample; the other columns (``ax..az``, ``gx..gz``, ``temp``,
``seq`` or any auxiliary name) take the latest value of their signal (NaN before its first
arrival). A ``seq`` signal counts drops with the signal's bit length as modulus.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

from ..io.recording import excerpt
from .candecoder import CanDecoder
from .counters import SeqTracker
from .sample import ACC_COLUMNS, GYRO_COLUMNS, Sample

NEEDS = 'decoding CAN frames through a DBC file needs cantools: pip install "mkc-stream[can-dbc]"'


class MappingError(ValueError):
    """A --map entry or DBC lookup that cannot work; the message says what to change."""


@dataclass(frozen=True)
class MapEntry:
    column: str
    message: str | None
    signal: str
    scale: float = 1.0


def parse_map(specs) -> list[MapEntry]:
    """Parse ``COLUMN=[MESSAGE.]SIGNAL[*SCALE]`` entries (strings, each possibly comma-separated)."""
    if isinstance(specs, str):
        specs = [specs]
    out: list[MapEntry] = []
    for spec in specs:
        for item in filter(None, (p.strip() for p in spec.split(","))):
            col, eq, rhs = item.partition("=")
            col, rhs = col.strip(), rhs.strip()
            if not eq or not col or not rhs:
                raise MappingError(f"--map entry {item!r} is not COLUMN=[MESSAGE.]SIGNAL[*SCALE]")
            if col == "t":
                raise MappingError("--map: t comes from the frame timestamp and cannot be mapped")
            sig, star, scale = rhs.partition("*")
            try:
                factor = float(scale) if star else 1.0
            except ValueError:
                raise MappingError(f"--map entry {item!r}: scale {scale!r} is not a number") from None
            msg, dot, name = sig.strip().rpartition(".")
            out.append(MapEntry(col, msg if dot else None, name, factor))
    cols = [e.column for e in out]
    dup = sorted({c for c in cols if cols.count(c) > 1})
    if dup:
        raise MappingError(f"--map maps {', '.join(dup)} more than once")
    missing = [c for c in ("mx", "my", "mz") if c not in cols]
    if missing:
        raise MappingError(f"--map must map mx, my and mz; missing {', '.join(missing)}")
    for group in (ACC_COLUMNS, GYRO_COLUMNS):
        if 0 < len(set(group) & set(cols)) < 3:
            raise MappingError(f"--map: map all of {', '.join(group)} or none")
    return out


def load_dbc(path):
    try:
        import cantools
    except ImportError:
        raise ImportError(NEEDS) from None
    if not os.path.isfile(path):
        raise MappingError(f"DBC file {path} not found")
    try:
        return cantools.database.load_file(str(path))
    except Exception as exc:  # noqa: BLE001 - cantools raises parser-specific errors
        raise MappingError(f"cannot read DBC file {path}: {exc}") from exc


class DbcDecoder(CanDecoder):
    name = "can-dbc"

    def __init__(self, dbc, mapping, host_time: bool = False):
        super().__init__(host_time)
        db = load_dbc(dbc) if isinstance(dbc, (str, os.PathLike)) else dbc
        entries = list(mapping)
        self.mapping = entries if entries and all(isinstance(m, MapEntry) for m in entries) else parse_map(entries)
        self._entries = []            # (column, message, signal name, scale)
        for e in self.mapping:
            self._entries.append((e.column, self._find(db, e), e.signal, e.scale))
        trig = {m.frame_id for c, m, _, _ in self._entries if c in ("mx", "my", "mz")}
        if len(trig) != 1:
            raise MappingError("--map: mx, my and mz must be signals of one message")
        self.trigger_id = trig.pop()
        self._messages = {m.frame_id: m for _, m, _, _ in self._entries}
        self._latest: dict[str, float] = {}
        self._mag = [next(x for x in self._entries if x[0] == c) for c in ("mx", "my", "mz")]
        cols = {e.column for e in self.mapping}
        self._acc = [next(x for x in self._entries if x[0] == c) for c in ACC_COLUMNS] if "ax" in cols else None
        self._gyro = [next(x for x in self._entries if x[0] == c) for c in GYRO_COLUMNS] if "gx" in cols else None
        self._temp = next((x for x in self._entries if x[0] == "temp"), None)
        seq = next((x for x in self._entries if x[0] == "seq"), None)
        self._seq_entry = seq
        self._seq = SeqTracker(1 << seq[1].get_signal_by_name(seq[2]).length) if seq else None
        fixed = {"mx", "my", "mz", "temp", "seq", *ACC_COLUMNS, *GYRO_COLUMNS}
        self._aux = [x for x in self._entries if x[0] not in fixed]
        mx = self._mag[0]
        unit = mx[1].get_signal_by_name(mx[2]).unit or ""
        self.units_mag = unit if mx[3] == 1.0 else (f"{unit} x {mx[3]:g}" if unit else "")
        self.meta = {"dbc_message": f"{mx[1].name} ({self.trigger_id:#x})",
                     "dbc_map": ",".join(f"{e.column}={e.message + '.' if e.message else ''}{e.signal}"
                                         f"{'*' + repr(e.scale) if e.scale != 1.0 else ''}" for e in self.mapping)}
        if self._seq is not None:
            self.meta["seq_modulus"] = str(self._seq.modulus)

    @staticmethod
    def _find(db, e: MapEntry):
        if e.message is not None:
            try:
                msg = db.get_message_by_name(e.message)
            except KeyError:
                raise MappingError(f"--map {e.column}: no message {e.message!r} in the DBC") from None
            if e.signal not in [s.name for s in msg.signals]:
                raise MappingError(f"--map {e.column}: message {e.message} has no signal {e.signal!r}; "
                                   f"it has {', '.join(s.name for s in msg.signals)}")
            return msg
        hits = [m for m in db.messages if e.signal in [s.name for s in m.signals]]
        if not hits:
            raise MappingError(f"--map {e.column}: no signal {e.signal!r} in the DBC")
        if len(hits) > 1:
            raise MappingError(f"--map {e.column}: signal {e.signal!r} is in messages "
                               f"{', '.join(m.name for m in hits)}; write MESSAGE.{e.signal}")
        return hits[0]

    def owns(self, msg) -> bool:
        return msg.arbitration_id in self._messages

    def _value(self, entry) -> float:
        return self._latest.get(entry[0], math.nan)

    def decode(self, msg) -> Sample | None:
        m = self._messages.get(msg.arbitration_id)
        if m is None:
            self.counts.ignored += 1
            return None
        try:
            values = m.decode(bytes(msg.data), decode_choices=False, scaling=True)
        except Exception as exc:  # noqa: BLE001 - cantools raises several error types for bad data
            self.count_bad(f"{m.name}: {excerpt(str(exc), 120, quote=False)}")
            return None
        for col, mm, sig, scale in self._entries:
            if mm is m:
                try:
                    self._latest[col] = float(values[sig]) * scale
                except (KeyError, TypeError, ValueError):
                    self._latest[col] = math.nan
        if msg.arbitration_id != self.trigger_id:
            return None
        self.counts.frames += 1
        mag = tuple(self._value(x) for x in self._mag)
        acc = tuple(self._value(x) for x in self._acc) if self._acc else None
        gyro = tuple(self._value(x) for x in self._gyro) if self._gyro else None
        temp = self._value(self._temp) if self._temp else None
        seq = None
        if self._seq is not None:
            v = self._value(self._seq_entry)
            if math.isfinite(v):
                seq = int(v)
                self._count_seq(self._seq, seq)
        aux = {x[0]: self._value(x) for x in self._aux} if self._aux else None
        return Sample(float(msg.timestamp), mag, acc, gyro, temp, seq, self.host_time, aux)

    def reset_stream(self):
        if self._seq is not None:
            self._seq.reset()
