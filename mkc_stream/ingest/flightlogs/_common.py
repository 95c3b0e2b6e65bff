"""What the flight-log readers share: format sniffing, the ``#instance=`` selector, alignment of
slower signals onto the magnetometer's timestamps, attitude conversions and the Recording build.

Alignment (``align``) is linear interpolation between the two source samples around each
magnetometer time, and NaN where there is no such pair (before the first, after the last) or where
the pair is further apart than ``GAP_FACTOR`` x the source's median step: a value is never carried
across a gap in the source.
"""
from __future__ import annotations

import contextlib
import io
import json
import pathlib
import re

import numpy as np

from ...io.recording import Recording, RecordingError
from ...recording_rules import GAP_FACTOR

#: first bytes of each binary format
ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_HEAD = b"\xa3\x95"
ROSBAG1_MAGIC = b"#ROSBAG V2.0"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"

#: suffix -> format when the suffix alone decides; .bin and .log are decided by content
BY_SUFFIX = {".ulg": "ulog", ".px4log": "px4log", ".tlog": "tlog", ".bag": "rosbag1",
             ".mcap": "rosbag2", ".db3": "rosbag2"}
AMBIGUOUS = (".bin", ".log")
EXTRA_OF = {"ulog": "ulog", "dataflash": "mavlink", "px4log": "mavlink", "tlog": "mavlink", "rosbag1": "ros",
            "rosbag2": "ros"}
LIBRARY_OF = {"ulog": "pyulog", "dataflash": "pymavlink", "px4log": "pymavlink", "tlog": "pymavlink",
              "rosbag1": "rosbags", "rosbag2": "rosbags"}

_SELECTOR = re.compile(r"^(?P<path>.+?)#(?P<opts>(?:instance|topic)=[^#]*)$")


class FlightLogError(RecordingError):
    """A flight log that cannot be read (empty, not the format its name says, no magnetometer)."""


def split_selector(text) -> tuple[pathlib.Path, dict]:
    """``LOG#instance=1`` or ``BAG#topic=/imu/mag`` -> (path, {"instance": "1"}); a file whose
    name really contains ``#`` is taken as it is."""
    text = str(text)
    m = _SELECTOR.match(text)
    if m is None or pathlib.Path(text).exists():
        return pathlib.Path(text), {}
    opts = {}
    for part in m.group("opts").split("&"):
        key, _, value = part.partition("=")
        if key not in ("instance", "topic") or not value:
            raise FlightLogError(f"{text}: the selector after '#' takes instance=ID or topic=NAME, got {part!r}")
        opts[key] = value
    return pathlib.Path(m.group("path")), opts


def _suffix(path: pathlib.Path) -> str:
    return path.suffix.lower()


def _head(path: pathlib.Path, n: int = 16) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def sniff_format(path) -> str | None:
    """The flight-log format of ``path`` by its suffix, and by its first bytes where the suffix is
    ambiguous (``.bin``, ``.log``: a candump ``.log`` is text, so it stays a CAN log); ``None``
    when it is not a flight log. A ROS 2 bag is its folder (with ``metadata.yaml``) or a file in it."""
    path, _ = split_selector(path)
    if path.is_dir():
        return "rosbag2" if (path / "metadata.yaml").is_file() else None
    suf = _suffix(path)
    if suf in AMBIGUOUS:
        head = _head(path) if path.is_file() else b""      # never read a pipe: its bytes would be gone
        if head.startswith(DATAFLASH_HEAD):
            return "dataflash"
        if head.startswith(ULOG_MAGIC):
            return "ulog"
        return None
    if suf in BY_SUFFIX:
        return BY_SUFFIX[suf]
    return None


def missing_library(fmt: str) -> ImportError:
    return ImportError(f"reading {fmt} logs needs {LIBRARY_OF[fmt]}: pip install \"mkc-stream[{EXTRA_OF[fmt]}]\" "
                       f"(or \"mkc-stream[logs]\" for every log format)")


@contextlib.contextmanager
def silenced_stderr_fd():
    """Silence file descriptor 2 (a C extension's prints, e.g. pymavlink's fast log indexer, whose
    complaints the parser repeats through Python, where :func:`captured_output` counts them)."""
    import os
    import sys
    import tempfile

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def said_lines(said: str, limit: int = 5) -> list[str]:
    """A reader's distinct complaints (numbers ignored), each once with how often it came."""
    counts: dict[str, list] = {}
    for line in said.splitlines():
        line = line.strip()
        if line:
            key = re.sub(r"\d+", "N", line)
            counts.setdefault(key, [line, 0])[1] += 1
    out = [f"{first[:120]}" + (f" (and {n - 1} more like it)" if n > 1 else "") for first, n in counts.values()]
    return out[:limit] + ([f"{len(out) - limit} other kinds of complaint"] if len(out) > limit else [])


@contextlib.contextmanager
def captured_output():
    """The readers print warnings about damage to stdout/stderr; they are collected here and
    reported as counted damage instead of being printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        yield out


# ----------------------------------------------------------------------------------------------
# alignment
# ----------------------------------------------------------------------------------------------

def _increasing(t_src: np.ndarray, v_src: np.ndarray):
    """Finite, strictly increasing source times (a repeated time keeps its first value)."""
    t_src = np.asarray(t_src, dtype=np.float64)
    v_src = np.asarray(v_src, dtype=np.float64)
    ok = np.isfinite(t_src)
    if v_src.ndim == 1:
        ok &= np.isfinite(v_src)
    else:
        ok &= np.all(np.isfinite(v_src), axis=1)
    t_src, v_src = t_src[ok], v_src[ok]
    order = np.argsort(t_src, kind="stable")
    t_src, v_src = t_src[order], v_src[order]
    keep = np.ones(t_src.shape[0], dtype=bool)
    keep[1:] = np.diff(t_src) > 0
    return t_src[keep], v_src[keep]


def align(t: np.ndarray, t_src, v_src, max_gap: float | None = None) -> np.ndarray:
    """``v_src`` (n,) or (n, k) at times ``t_src``, interpolated linearly onto ``t``:
    v(t) = v0 + (t - t0) / (t1 - t0) * (v1 - v0) for the source pair t0 <= t <= t1 around t;
    NaN outside the source's span, where a value is missing, and across a pair further apart than
    ``max_gap`` (default GAP_FACTOR x the source's median step)."""
    t = np.asarray(t, dtype=np.float64)
    ts, vs = _increasing(t_src, v_src)
    shape = (t.shape[0],) + vs.shape[1:]
    out = np.full(shape, np.nan)
    if ts.shape[0] == 0:
        return out
    if ts.shape[0] == 1:
        out[t == ts[0]] = vs[0]
        return out
    if max_gap is None:
        max_gap = GAP_FACTOR * float(np.median(np.diff(ts)))
    i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.shape[0] - 2)
    t0, t1 = ts[i], ts[i + 1]
    inside = (t >= ts[0]) & (t <= ts[-1]) & ((t1 - t0) <= max_gap)
    w = (t - t0) / (t1 - t0)
    if vs.ndim > 1:
        w = w[:, None]
    val = vs[i] + w * (vs[i + 1] - vs[i])
    out[inside] = val[inside]
    return out


def align_quaternion(t, t_src, q_src) -> np.ndarray:
    """Unit quaternions (n, 4) onto ``t``: signs made continuous (q and -q are one rotation), then
    :func:`align` component-wise and renormalised (a good approximation of slerp between close
    samples; NaN rows where :func:`align` gives NaN)."""
    ts, q = _increasing(t_src, q_src)
    if q.shape[0] > 1:
        flip = np.cumsum(np.einsum("ij,ij->i", q[1:], q[:-1]) < 0) % 2
        q = q.copy()
        q[1:][flip == 1] *= -1
    out = align(t, ts, q)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return out / norm


def quat_from_euler(roll, pitch, yaw) -> np.ndarray:
    """(n, 4) Hamilton quaternions, scalar first, of the aerospace Z-Y-X Euler angles (rad): they
    rotate body (FRD) vectors into north-east-down, q = q_z(yaw) q_y(pitch) q_x(roll)."""
    cr, sr = np.cos(np.asarray(roll) / 2), np.sin(np.asarray(roll) / 2)
    cp, sp = np.cos(np.asarray(pitch) / 2), np.sin(np.asarray(pitch) / 2)
    cy, sy = np.cos(np.asarray(yaw) / 2), np.sin(np.asarray(yaw) / 2)
    return np.stack([cr * cp * cy + sr * sp * sy,
                     sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy], axis=1)


# ----------------------------------------------------------------------------------------------
# the recording
# ----------------------------------------------------------------------------------------------

def build_recording(path, t, mag, aux: dict, meta: dict, damage: list[tuple[int, str]]) -> Recording:
    """The Recording of one magnetometer stream: samples whose time or field is not finite, and
    samples whose time goes back, become bad rows (``(index, reason)``: the sample's index in the
    log's magnetometer stream) beside the reader's ``damage``; nothing else is left out."""
    t = np.asarray(t, dtype=np.float64)
    mag = np.asarray(mag, dtype=np.float64).reshape(-1, 3)
    bad = list(damage)
    ok = np.isfinite(t) & np.all(np.isfinite(mag), axis=1)
    for i in np.flatnonzero(~ok):
        bad.append((int(i), "non-finite: the magnetometer sample or its time is not a number"))
    idx = np.flatnonzero(ok)
    if idx.size > 2:               # a lone time far ahead of both neighbours (a damaged time field)
        tt = t[idx]
        spike = np.zeros(idx.size, dtype=bool)
        spike[1:-1] = (tt[1:-1] > tt[2:]) & (tt[:-2] <= tt[2:])
        for i in idx[spike]:
            bad.append((int(i), "t decreasing: a time ahead of both neighbours (a damaged time field)"))
        ok[idx[spike]] = False
        idx = idx[~spike]
    if idx.size:
        running = np.maximum.accumulate(t[idx])
        back = np.zeros(idx.size, dtype=bool)
        back[1:] = t[idx][1:] < running[:-1]
        for i in idx[back]:
            bad.append((int(i), "t decreasing: the log's time goes back"))
        ok[idx[back]] = False
    aux = {k: np.asarray(v, dtype=np.float64)[ok] for k, v in aux.items()}
    meta = {k: v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()}
    meta.setdefault("units.mag", "uT")
    return Recording(t[ok], mag[ok], aux, meta, bad, pathlib.Path(path))


def rate_of(t: np.ndarray) -> float | None:
    """Mean sample rate (Hz) over the stream: (n - 1) / duration."""
    if len(t) < 2 or not t[-1] > t[0]:
        return None
    return (len(t) - 1) / float(t[-1] - t[0])
