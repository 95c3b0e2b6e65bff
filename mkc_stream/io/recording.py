"""The recording file: the interchange CSV every mkc_stream command reads and writes.

Format (the project's recording spec)::

    # sensor: QMC5883L          <- optional metadata lines first, each "# key: value"
    # units.mag: counts
    t,mx,my,mz,ax,ay,az,temp    <- one header row; t, mx, my, mz are required
    0,6242,980,3872,0.01,...    <- one row per sample

* An empty cell or ``nan`` is a missing value. Optional columns keep it as NaN.
* A row is *bad input* when a required cell (t, mx, my, mz) is missing, not a number or not
  finite, when a cell of any column is not a number (garbled line), when it has the wrong number
  of cells, when it is the cut-off last line of a truncated file, or when its ``t`` is smaller
  than the largest ``t`` accepted before it (time must be non-decreasing; rows are never
  reordered). Bad rows are left out of the arrays and listed in :attr:`Recording.bad_rows` as
  ``(line number, reason)`` with 1-based file line numbers; nothing is dropped silently and
  nothing is invented. Each reason starts with a kind (``"non-numeric"``, ``"missing"``,
  ``"non-finite"``, ``"cell count"``, ``"truncated"``, ``"t decreasing"``, ``"unexpected
  comment"``, ``"dropout"``) followed by ``": "`` and the details.
* Blank lines carry no sample and are skipped. A last line without a line ending is accepted when
  it parses completely (it cannot be told from a complete row); a ``.gz`` stream that ends early
  always makes its last line bad, and a corrupt one (a failed gzip check) is not read at all
  (deflate cannot say where the damage starts).
* Metadata lines and the header row hold at most :data:`MAX_HEADER_LINE` bytes each and no NUL
  byte; an input breaking this is binary, not a recording, and is refused after a bounded read.
  A metadata key given twice with different values is an error (which one holds is unknown).
* ``units.mag`` is free text (default ``uT``); :data:`UT_UNITS` are microtesla, for which the
  calibration checks the fitted field against Earth's (15-100 uT); :data:`OTHER_MAG_UNITS`
  (``counts``, ``raw``, ``G`` ...) are read the same but skip that check, and any other value
  gives a :class:`RecordingWarning`: the fit does not depend on the unit, so refusing the file
  would refuse good data, but skipping the check must not be silent.
* Error messages quote at most 80 characters of the input (:func:`excerpt`).
* A gap is a time step larger than :data:`GAP_FACTOR` (2.5) times the median positive time step
  (a robust nominal period that ignores the gaps themselves); :meth:`Recording.counts` reports
  how many there are.

:func:`write_recording` writes every float with ``repr`` (shortest string that round-trips), so
``read_recording(write_recording(...))`` returns bit-identical arrays.

The loaders of the public third-party datasets (``load_*``) are in :mod:`mkc_stream.io.datasets`;
their names still resolve here for older imports.

Size: one module is the whole format (the in-memory recording, the bounded reader of hostile
input, the writer, the bundled recordings): its rules are stated once, above, and kept in one place.
"""
from __future__ import annotations

import contextlib
import gzip
import io
import math
import os
import pathlib
import re
import tempfile
import warnings
import zlib
from dataclasses import dataclass, field
from typing import ClassVar, Iterable, Mapping

import numpy as np

from ..recording_rules import GAP_FACTOR, REQUIRED
from ..units import MICROTESLA, OTHER_MAG_UNITS

__all__ = [
    "GAP_FACTOR",
    "REQUIRED",
    "Recording",
    "RecordingError",
    "RecordingWarning",
    "bundled_recording",
    "bundled_recording_path",
    "bundled_recordings",
    "excerpt",
    "read_recording",
    "write_recording",
]


class RecordingError(ValueError):
    """The file cannot be read as a recording at all (no header, missing required column, ...)."""


# ----------------------------------------------------------------------------------------------
# the in-memory recording
# ----------------------------------------------------------------------------------------------


@dataclass
class Recording:
    """A recorded stream: time, raw magnetometer, auxiliary signals, metadata and bad rows.

    ``t`` (N,) float64 seconds, non-decreasing; ``mag`` (N, 3) float64 raw magnetometer in
    :attr:`mag_unit`; ``aux`` maps every other column name (``ax``..``gz``, ``temp``,
    ``current``, ``throttle``, ``voltage`` or any other name) to an (N,) float64 array with NaN
    for missing cells; ``meta`` holds the ``# key: value`` lines (unknown keys kept);
    ``bad_rows`` lists ``(line number, reason)`` of every row left out; ``path`` is where it was
    read from (``None`` when built in memory).
    """

    t: np.ndarray
    mag: np.ndarray
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)
    bad_rows: list[tuple[int, str]] = field(default_factory=list)
    path: pathlib.Path | None = None

    GAP_FACTOR: ClassVar[float] = GAP_FACTOR

    def __post_init__(self):
        self.t = np.ascontiguousarray(self.t, dtype=np.float64).reshape(-1)
        n = self.t.shape[0]
        self.mag = np.ascontiguousarray(self.mag, dtype=np.float64)
        if self.mag.shape != (n, 3):
            raise ValueError(f"mag must have shape ({n}, 3) to match t, got {self.mag.shape}")
        aux = {}
        for name, col in dict(self.aux).items():
            col = np.ascontiguousarray(col, dtype=np.float64).reshape(-1)
            if col.shape != (n,):
                raise ValueError(f"aux column {name!r} has {col.shape[0]} values, expected {n}")
            aux[str(name)] = col
        self.aux = aux
        self.meta = {str(k): str(v) for k, v in dict(self.meta).items()}
        self.bad_rows = [(int(line), str(reason)) for line, reason in self.bad_rows]
        if self.path is not None:
            self.path = pathlib.Path(self.path)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __repr__(self) -> str:
        src = f", path={str(self.path)!r}" if self.path is not None else ""
        return (f"Recording(samples={len(self)}, aux={list(self.aux)}, bad_rows={len(self.bad_rows)}, "
                f"mag_unit={self.mag_unit!r}{src})")

    @property
    def mag_unit(self) -> str:
        """Unit of :attr:`mag`, from the ``units.mag`` metadata (default ``"uT"``)."""
        return self.meta.get("units.mag", "uT") or "uT"

    @property
    def columns(self) -> list[str]:
        """Column names in file order: ``t, mx, my, mz`` then the auxiliary columns."""
        return list(REQUIRED) + list(self.aux)

    @property
    def rate_hz(self) -> float | None:
        """The ``rate_hz`` metadata if it is a number, else 1 / median positive time step."""
        with contextlib.suppress(KeyError, ValueError):
            rate = float(self.meta["rate_hz"])
            if math.isfinite(rate) and rate > 0:
                return rate
        dt = np.diff(self.t)
        dt = dt[dt > 0]
        return float(1.0 / np.median(dt)) if dt.size else None

    def gap_indices(self) -> np.ndarray:
        """Indices ``i`` such that ``t[i+1] - t[i]`` exceeds GAP_FACTOR x the median positive step."""
        dt = np.diff(self.t)
        pos = dt[dt > 0]
        if pos.size < 2:
            return np.zeros(0, dtype=np.intp)
        return np.flatnonzero(dt > self.GAP_FACTOR * float(np.median(pos)))

    def counts(self) -> dict[str, int]:
        """``{"samples": N, "bad_frames": bad rows, "drops": 0, "gaps": time gaps}``.

        ``drops`` (frames lost by a live transport) is always 0 for a file.
        """
        return {
            "samples": len(self),
            "bad_frames": len(self.bad_rows),
            "drops": 0,
            "gaps": int(self.gap_indices().size),
        }

    def bad_summary(self) -> dict[str, int]:
        """Number of bad rows by kind (the part of each reason before the first ``": "``)."""
        out: dict[str, int] = {}
        for _, reason in self.bad_rows:
            kind = reason.split(": ", 1)[0]
            out[kind] = out.get(kind, 0) + 1
        return out

    def write(self, path) -> pathlib.Path:
        """Write this recording with :func:`write_recording` (bad rows are not written)."""
        return write_recording(path, self.t, self.mag, self.aux, self.meta)


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------


#: bytes of one metadata or header line; a longer one is not a recording (a transposed table,
#: binary data): reading stops there instead of echoing or splitting megabytes of garbage
MAX_HEADER_LINE = 65536
#: bytes of (decompressed) text read at most: an endless input (``/dev/zero``) or a gzip bomb
#: ends with an error instead of filling the memory (2 GiB is ~40 million rows)
MAX_INPUT_BYTES = 2 << 30
_READ = 1 << 20
_GZ_MAGIC = b"\x1f\x8b"
_EOL = re.compile(rb"\r\n?|\n")


def excerpt(text, limit: int = 80, quote: bool = True) -> str:
    """``text`` (str or bytes) for a message, quoted unless ``quote`` is False: at most ``limit``
    characters, control characters escaped, and how much was left out. Error messages never
    echo more of an input."""
    unit = "bytes" if isinstance(text, (bytes, bytearray)) else "characters"
    head = text[:limit]
    if unit == "bytes":
        head = bytes(head).decode("utf-8", "replace")
    shown = "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in head)
    more = len(text) - limit
    q = "'" if quote else ""
    return f"{q}{shown}{q}" + (f"... ({more} more {unit})" if more > 0 else "")


def _open_chunks(path: pathlib.Path, state: dict):
    """Decompressed content of ``path`` in chunks, gunzipped when it is gzip (by magic bytes).

    Sets ``state["damage"]`` when a gzip stream ends early (a cut file: what came before is
    right); a corrupt one (a failed check) raises :class:`RecordingError`.
    """
    try:
        f = open(path, "rb")
    except IsADirectoryError:
        raise RecordingError(f"{path} is a directory, not a recording file") from None
    with f:
        data = f.read(_READ)
        if data[:2] != _GZ_MAGIC:
            while data:
                yield data
                data = f.read(_READ)
            return
        state["gzip"] = True
        yield from _gunzip(f, data, state, path)


def _gunzip(f, data: bytes, state: dict, path):
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    while True:
        try:
            out = d.decompress(data, _READ)    # bounded output per call: a gzip bomb is read in steps
        except zlib.error as exc:
            # deflate cannot say where damage starts: what came before it may be wrong too
            raise RecordingError(f"{path}: the gzip stream is corrupt ({exc}); its content cannot be "
                                 f"trusted, so it is not read") from None
        data = d.unconsumed_tail
        if out:
            yield out
        if d.eof:
            data = d.unused_data or f.read(_READ)
            if len(data) == 1:
                data += f.read(1)
            if data[:2] != _GZ_MAGIC:          # the end, or padding after the last member
                return
            d = zlib.decompressobj(16 + zlib.MAX_WBITS)
        elif not data and not out:
            data = f.read(_READ)
            if not data:
                state["damage"] = "the gzip stream is truncated (it ends before its end marker)"
                return


class _PreambleCheck:
    """Checks the lines up to the header row while the bytes arrive, so that a binary or endless
    input is refused after a bounded read: each such line holds at most MAX_HEADER_LINE bytes and
    no NUL byte. Line ends are those of :func:`_decode` (``\\r\\n``, ``\\r``, ``\\n``)."""

    def __init__(self, path):
        self.path = path
        self.pos = 0          # start of the line being checked
        self.seen = 0         # bytes before this hold no line end and no NUL (each byte is scanned once)
        self.lineno = 0
        self.done = False

    def feed(self, buf: bytearray, eof: bool):
        if self.pos == 0 and self.lineno == 0 and buf[:2] in (b"\xff\xfe", b"\xfe\xff"):
            raise RecordingError(f"{self.path}: UTF-16 text; a recording is UTF-8 (or ASCII) text")
        while not self.done:
            start = max(self.pos, self.seen)
            m = _EOL.search(buf, start, min(len(buf), self.pos + MAX_HEADER_LINE + 2))
            if m is not None and m.group() == b"\r" and m.end() == len(buf) and not eof:
                m = None                        # may be the first half of \r\n
            if m is None:
                tail = len(buf) - self.pos
                if tail > MAX_HEADER_LINE:
                    self._check(buf, self.pos, self.pos + MAX_HEADER_LINE + 1, self.lineno + 1)
                if eof:
                    if tail:                    # the header row without a line ending
                        self._check(buf, self.pos, len(buf), self.lineno + 1)
                        self.done = bool(buf[self.pos:].strip())
                    return
                if buf.find(b"\0", start) >= 0:
                    self._check(buf, self.pos, len(buf), self.lineno + 1)
                self.seen = max(self.pos, len(buf) - 1)   # a final \r is looked at again
                return
            self.lineno += 1
            self._check(buf, self.pos, m.start(), self.lineno)
            line = bytes(buf[self.pos:m.start()]).strip()
            self.pos = m.end()
            if line.startswith(b"\xef\xbb\xbf"):
                line = line[3:].strip()
            if line and not line.startswith(b"#"):
                self.done = True

    def _check(self, buf, a, b, lineno):
        if buf.find(b"\0", a, b) >= 0:
            raise RecordingError(f"{self.path}: line {lineno} holds NUL bytes before the header row: "
                                 f"binary data, not a recording (a text CSV)")
        if b - a > MAX_HEADER_LINE:
            raise RecordingError(f"{self.path}: line {lineno} is longer than {MAX_HEADER_LINE} bytes before "
                                 f"the header row ends (it starts {excerpt(bytes(buf[a:a + 40]))}...): "
                                 f"not a recording (a transposed table or binary data?)")


def _read_input(path: pathlib.Path, check_preamble: bool = False) -> tuple[bytearray, str | None]:
    """The (gunzipped) bytes of ``path`` and why a gzip stream ended early (None when it did not).

    At most MAX_INPUT_BYTES are read; with ``check_preamble`` the lines up to the header row are
    checked as they arrive (:class:`_PreambleCheck`).
    """
    state: dict = {}
    buf = bytearray()
    pre = _PreambleCheck(path) if check_preamble else None
    for chunk in _open_chunks(path, state):
        buf += chunk
        if len(buf) > MAX_INPUT_BYTES:
            raise RecordingError(f"{path}: more than {MAX_INPUT_BYTES >> 20} MiB of text; too large for "
                                 f"a recording (or an endless input)")
        if pre is not None and not pre.done:
            pre.feed(buf, False)
    if pre is not None and not pre.done:
        pre.feed(buf, True)
    damage = state.get("damage")
    if damage is not None and not buf:
        raise RecordingError(f"{path}: {damage}, and holds no data; not a readable recording")
    return buf, damage


def _read_bytes(path: pathlib.Path) -> tuple[bytes, bool]:
    """File content, gunzipped when it is gzip (by magic bytes); True if the gz stream ends early."""
    buf, damage = _read_input(path)
    return bytes(buf), damage is not None


def _decode(data) -> str:
    text = data.decode("utf-8", errors="replace")
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    return text


def _cell_value(cell: str) -> float | None:
    """float of a cell; NaN for an empty cell or nan; None when it is not a number."""
    c = cell.strip()
    if not c:
        return math.nan
    try:
        return float(c)
    except ValueError:
        return None


_CHUNK = 32768  # lines per numpy parse; a chunk with a bad line is re-parsed line by line


def _parse_body(body: str, first_line: int, names: list[str], required: Iterable[int],
                stream_truncated: bool) -> tuple[np.ndarray, np.ndarray, list[tuple[int, str]]]:
    """Parse the data rows of a comma-separated body.

    Returns ``(values (n, ncol), file line numbers (n,), bad rows)``: the rows kept, their line
    numbers and the bad rows with reasons. ``first_line`` is the file line number of the first
    body line. Required cells must be finite numbers.

    Speed: chunks of lines go through numpy's C parser; it refuses empty cells, wrong cell
    counts and non-numbers and skips blank lines, so a chunk is only trusted when it gave exactly
    one row per line, and is otherwise parsed line by line in Python. The last non-blank line is
    always parsed on its own (it may be cut short).
    """
    ncol = len(names)
    required = list(required)
    ends_with_newline = body.endswith("\n")
    lines = body.split("\n")
    if ends_with_newline:
        lines.pop()  # the empty string after the final line ending
    last = len(lines) - 1
    while last >= 0 and not lines[last].strip():
        last -= 1
    cut = stream_truncated or not ends_with_newline  # the last non-blank line may be cut short

    blocks: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    bad: list[tuple[int, str]] = []
    for start in range(0, max(last, 0), _CHUNK):
        stop = min(start + _CHUNK, last)
        chunk = lines[start:stop]
        arr = None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                arr = np.loadtxt(io.StringIO("\n".join(chunk)), delimiter=",", dtype=np.float64,
                                 comments=None, ndmin=2, quotechar=None)
        except ValueError:
            pass
        if arr is not None and arr.shape == (len(chunk), ncol):
            blocks.append(arr)
            labels.append(np.arange(first_line + start, first_line + stop))
        else:
            a, lab = _parse_lines(chunk, first_line + start, names, bad, False, False)
            blocks.append(a)
            labels.append(lab)
    if last >= 0:
        a, lab = _parse_lines(lines[last:last + 1], first_line + last, names, bad, cut, stream_truncated)
        blocks.append(a)
        labels.append(lab)
    data = np.concatenate(blocks) if blocks else np.zeros((0, ncol))
    linenos = np.concatenate(labels) if labels else np.zeros(0, dtype=np.intp)

    # required cells must be finite numbers
    if data.shape[0] and required:
        req = data[:, required]
        bad_req = ~np.isfinite(req).all(axis=1)
        if bad_req.any():
            for i in np.flatnonzero(bad_req):
                j = next(k for k in range(len(required)) if not math.isfinite(req[i, k]))
                v = float(req[i, j])
                col = names[required[j]]
                if math.isnan(v):
                    reason = f"missing: required column {col!r} is empty or nan"
                else:
                    reason = f"non-finite: required column {col!r} is {v!r}"
                bad.append((int(linenos[i]), reason))
            data = data[~bad_req]
            linenos = linenos[~bad_req]
    return data, linenos, bad


def _parse_lines(lines: list[str], first_line: int, names: list[str], bad: list[tuple[int, str]],
                 is_last_cut: bool, stream_truncated: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-line parser: every malformed line becomes a bad row (appended to ``bad``).

    ``is_last_cut``: ``lines`` is the file's last line and may have been cut mid-row;
    ``stream_truncated``: it certainly was (compressed stream ended early).
    """
    ncol = len(names)
    rows: list[list[float]] = []
    linenos: list[int] = []
    for k, line in enumerate(lines):
        lineno = first_line + k
        cells = line.split(",")
        reason = None
        vals: list[float] = []
        if not line.strip():
            continue
        if line.lstrip().startswith("#"):
            reason = "unexpected comment: comment line after the header"
        elif len(cells) != ncol:
            reason = f"cell count: expected {ncol} cells, got {len(cells)}"
        else:
            for name, cell in zip(names, cells):
                v = _cell_value(cell)
                if v is None:
                    shown = cell.strip()
                    shown = shown if len(shown) <= 40 else shown[:37] + "..."
                    reason = f"non-numeric: column {name!r} has {shown!r}"
                    break
                vals.append(v)
        if reason is not None and is_last_cut:
            reason = f"truncated: last line ends mid-row ({reason})"
        elif reason is None and stream_truncated:
            reason = "truncated: last line of a compressed stream that ends early"
        if reason is not None:
            bad.append((lineno, reason))
        else:
            rows.append(vals)
            linenos.append(lineno)
    data = np.array(rows, dtype=np.float64).reshape(len(rows), ncol)
    return data, np.array(linenos, dtype=np.intp)


def _decreasing(t: np.ndarray) -> np.ndarray:
    """Mask of samples whose t is below the largest t before them (NaN-free input)."""
    bad = np.zeros(t.shape, dtype=bool)
    if t.size > 1:
        cummax = np.maximum.accumulate(t)
        bad[1:] = t[1:] < cummax[:-1]
    return bad


def _drop_decreasing(t, keep_cols, labels, bad, what="t"):
    """Remove samples whose time goes backwards; add them to ``bad`` with ``labels`` as line numbers."""
    dec = _decreasing(t)
    if dec.any():
        cummax = np.maximum.accumulate(t)
        for i in np.flatnonzero(dec):
            bad.append((int(labels[i]), f"t decreasing: {what}={float(t[i])!r} is below the earlier "
                                        f"{what}={float(cummax[i - 1])!r}"))
        keep = ~dec
        t = t[keep]
        keep_cols = [c[keep] for c in keep_cols]
        labels = labels[keep]
    return t, keep_cols, labels


def _parse_meta_line(line: str, meta: dict[str, str], where: dict[str, int] | None = None,
                     lineno: int = 0, path=None) -> None:
    content = line.strip()[1:].strip()
    if not content:
        return
    if ":" in content:
        key, value = content.split(":", 1)
        key = key.strip()
        value = value.strip()
        if key == "comment":          # notes accumulate, as free-text lines do: never a conflict
            content = value
        elif key:
            if where is not None and key in meta and meta[key] != value:
                # which line holds is unknown: keeping either would be a silent guess
                raise RecordingError(
                    f"{path}: lines {where[key]} and {lineno}: metadata {excerpt(key, 40)} is given twice "
                    f"with different values, {excerpt(meta[key], 40)} and {excerpt(value, 40)}")
            meta[key] = value
            if where is not None:
                where.setdefault(key, lineno)
            return
    meta["comment"] = f"{meta['comment']}; {content}" if "comment" in meta else content


#: ``units.mag`` values read as microtesla (the unit of the physical field-range check) and the
#: spec's other units: one list, in mkc_stream/units.py
UT_UNITS, OTHER_MAG_UNITS = MICROTESLA, OTHER_MAG_UNITS


class RecordingWarning(UserWarning):
    """The recording is read, but something in it deserves a look (an unknown unit ...)."""


def _check_unit(path, meta: dict[str, str]) -> None:
    """Warn about a ``units.mag`` the spec does not name: the field-range check is then skipped."""
    unit = meta.get("units.mag", "").strip()
    known = {u.lower() for u in UT_UNITS + OTHER_MAG_UNITS}
    if unit and unit.lower() not in known:
        warnings.warn(f"{path}: unknown magnetometer unit {excerpt(unit, 40)} (units.mag); the fit does not "
                      f"depend on it, but the field-range check of uT data is skipped (known units: "
                      f"{', '.join(UT_UNITS + OTHER_MAG_UNITS)})", RecordingWarning, stacklevel=3)


def _header(text: str, path, damage: str | None) -> tuple[dict[str, str], str, int, int]:
    """``(meta, header row, its line number, where the body starts)``: metadata lines, then the header.

    Each such line holds at most MAX_HEADER_LINE characters and no NUL (:class:`_PreambleCheck`
    refuses them earlier on bytes; this is the same rule on the decoded text).
    """
    meta: dict[str, str] = {}
    where: dict[str, int] = {}
    pos = 0
    lineno = 0
    n = len(text)
    while pos < n:
        end = text.find("\n", pos, pos + MAX_HEADER_LINE + 1)
        if end < 0:
            end = n if n - pos <= MAX_HEADER_LINE else pos + MAX_HEADER_LINE + 1
        line = text[pos:end]
        lineno += 1
        if "\0" in line:
            raise RecordingError(f"{path}: line {lineno} holds NUL bytes before the header row: "
                                 f"binary data, not a recording (a text CSV)")
        if len(line) > MAX_HEADER_LINE:
            raise RecordingError(f"{path}: line {lineno} is longer than {MAX_HEADER_LINE} characters before "
                                 f"the header row ends (it starts {excerpt(line[:40])}...): not a recording "
                                 f"(a transposed table or binary data?)")
        pos = end + 1
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            _parse_meta_line(s, meta, where, lineno, path)
            continue
        return meta, line, lineno, pos
    what = "is empty" if not meta else "holds only metadata lines (no header row)"
    note = f" ({damage})" if damage else ""
    raise RecordingError(f"{path}: the file {what}{note}; a recording needs a header row "
                         f"with at least {','.join(REQUIRED)} and data rows")


def read_recording(path) -> Recording:
    """Read a recording file (``.csv`` or ``.csv.gz``; gzip is recognised by its magic bytes).

    Raises :class:`RecordingError` for a file that is empty, holds only metadata, has a malformed
    header, lacks a required column (``t``, ``mx``, ``my``, ``mz``), gives one metadata key two
    different values, is a directory, is binary (a NUL byte, or a line longer than
    MAX_HEADER_LINE bytes, before the header row ends), is a gzip stream damaged before any data,
    or holds more than MAX_INPUT_BYTES; an input is read only as far as needed to tell. Bad rows
    never raise: they are reported in :attr:`Recording.bad_rows` (see the module documentation
    for the rules). A ``units.mag`` that the spec does not name gives a :class:`RecordingWarning`.
    Time and memory are linear in the size of the input.
    """
    path = pathlib.Path(path)
    data, damage = _read_input(path, check_preamble=True)
    truncated = damage is not None
    text = _decode(data)
    del data
    meta, header, header_line, pos = _header(text, path, damage)
    names = [c.strip() for c in header.split(",")]
    if any(not n for n in names):
        raise RecordingError(f"{path}: line {header_line}: empty column name in header {excerpt(header.strip())}")
    seen: set[str] = set()
    dup = sorted({n for n in names if n in seen or seen.add(n)})   # linear: a header may be huge
    if dup:
        shown = ", ".join(excerpt(n, 40) for n in dup[:5]) + (f" and {len(dup) - 5} more" if len(dup) > 5 else "")
        raise RecordingError(f"{path}: line {header_line}: duplicate column name(s) {shown} in header")
    missing = [c for c in REQUIRED if c not in seen]
    if missing:
        raise RecordingError(
            f"{path}: line {header_line}: missing required column(s) {', '.join(missing)}; "
            f"the header has {len(names)} column(s), {excerpt(', '.join(names))}, "
            f"but a recording needs {', '.join(REQUIRED)}")
    _check_unit(path, meta)

    body = text[pos:] if pos <= len(text) else ""
    del text
    req_idx = [names.index(c) for c in REQUIRED]
    values, linenos, bad = _parse_body(body, header_line + 1, names, req_idx, truncated)
    del body
    t = values[:, req_idx[0]]
    t, (values,), linenos = _drop_decreasing(t, [values], linenos, bad)
    bad.sort(key=lambda b: b[0])
    mag = values[:, req_idx[1:]]
    aux = {n: np.ascontiguousarray(values[:, j]) for j, n in enumerate(names) if n not in REQUIRED}
    return Recording(t=np.ascontiguousarray(t), mag=np.ascontiguousarray(mag), aux=aux, meta=meta,
                     bad_rows=bad, path=path)


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------


def _format_column(col: np.ndarray) -> list[str]:
    """Shortest round-tripping text of each value (``repr``), integers without a trailing ``.0``."""
    out = list(map(float.__repr__, col.tolist()))
    return [s[:-2] if s.endswith(".0") else s for s in out]


def _check_name(name: str, what: str) -> str:
    name = str(name)
    if not name or name != name.strip() or any(ch in name for ch in ",\n\r"):
        raise ValueError(f"{what} {name!r} must be non-empty, without commas, line breaks or "
                         f"surrounding spaces")
    return name


def _file_mode(path: pathlib.Path) -> int:
    """Permissions for a new file: the existing file's, else 0o666 minus the umask."""
    with contextlib.suppress(OSError):
        return path.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def write_recording(path, t, mag, aux: Mapping[str, np.ndarray] | None = None,
                    meta: Mapping[str, object] | None = None) -> pathlib.Path:
    """Write a recording file; gzip-compressed when the name ends in ``.gz``.

    Columns are ``t, mx, my, mz`` then the ``aux`` columns in their order; ``meta`` becomes the
    ``# key: value`` lines (values are written with ``str`` and read back stripped). Floats are
    written with ``repr`` so a read gives back bit-identical arrays (NaN is written ``nan``).
    The file is written to a temporary name and renamed, so a reader never sees half a file.
    Returns the path.
    """
    path = pathlib.Path(path)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    mag = np.asarray(mag, dtype=np.float64)
    n = t.shape[0]
    if mag.shape != (n, 3):
        raise ValueError(f"mag must have shape ({n}, 3) to match t, got {mag.shape}")
    cols = [t, mag[:, 0], mag[:, 1], mag[:, 2]]
    names = list(REQUIRED)
    for name, col in (aux or {}).items():
        name = _check_name(name, "aux column name")
        if name in names or name.startswith("#"):
            raise ValueError(f"aux column name {name!r} clashes with another column or a comment")
        col = np.asarray(col, dtype=np.float64).reshape(-1)
        if col.shape != (n,):
            raise ValueError(f"aux column {name!r} has {col.shape[0]} values, expected {n}")
        names.append(name)
        cols.append(col)
    lines = []
    for key, value in (meta or {}).items():
        key = _check_name(key, "metadata key")
        value = str(value)
        if ":" in key or key.startswith("#"):
            raise ValueError(f"metadata key {key!r} must not contain ':' or start with '#'")
        if "\n" in value or "\r" in value:
            raise ValueError(f"metadata value of {key!r} must be a single line")
        lines.append(f"# {key}: {value}".rstrip() + "\n")
    lines.append(",".join(names) + "\n")
    text_cols = [_format_column(c) for c in cols]
    head = "".join(lines)
    body = "\n".join(map(",".join, zip(*text_cols)))
    payload = (head + body + ("\n" if n else "")).encode("utf-8")

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if path.name.lower().endswith(".gz"):
                with gzip.GzipFile(filename="", mode="wb", fileobj=f, mtime=0, compresslevel=6) as gz:
                    gz.write(payload)
            else:
                f.write(payload)
        os.chmod(tmp, _file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


# ----------------------------------------------------------------------------------------------
# the bundled recording(s)
# ----------------------------------------------------------------------------------------------

_RESOURCE_STACK = contextlib.ExitStack()


def bundled_recordings() -> list[str]:
    """Names of the recordings shipped in ``mkc_stream/data``."""
    from importlib import resources

    d = resources.files("mkc_stream").joinpath("data")
    return sorted(p.name for p in d.iterdir() if p.name.endswith((".csv", ".csv.gz")))


def bundled_recording_path(name: str = "qmc5883l_noisy.csv") -> pathlib.Path:
    """Filesystem path of a recording shipped with the package (``mkc_stream/data/<name>``).

    The default is the real QMC5883L recording (MIT, see ``mkc_stream/data/LICENSES.md``).
    """
    from importlib import resources

    ref = resources.files("mkc_stream").joinpath("data").joinpath(name)
    if not ref.is_file():
        raise FileNotFoundError(f"no bundled recording {name!r}; available: {bundled_recordings()}")
    if isinstance(ref, os.PathLike):
        return pathlib.Path(os.fspath(ref))
    # installed in a zip: extract once, kept until the interpreter exits
    import atexit

    if not getattr(_RESOURCE_STACK, "_registered", False):
        atexit.register(_RESOURCE_STACK.close)
        _RESOURCE_STACK._registered = True  # type: ignore[attr-defined]
    return pathlib.Path(_RESOURCE_STACK.enter_context(resources.as_file(ref)))


def bundled_recording(name: str = "qmc5883l_noisy.csv") -> Recording:
    """:func:`read_recording` of :func:`bundled_recording_path`."""
    return read_recording(bundled_recording_path(name))


# ----------------------------------------------------------------------------------------------
# the dataset loaders moved to mkc_stream.io.datasets; their old names here still resolve
# ----------------------------------------------------------------------------------------------

_MOVED_TO_DATASETS = frozenset({
    "load_broad", "load_cave_survey_json", "load_ck_explorer_csv", "load_qmc5883l_csv", "load_rasteiro_mat",
})


def __getattr__(name: str):
    # ``from mkc_stream.io.recording import load_broad`` and ``R.load_broad`` keep working (used by
    # tests/ and tools/); resolved lazily so this module does not import mkc_stream.io.datasets.
    if name in _MOVED_TO_DATASETS:
        from . import datasets

        return getattr(datasets, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
