"""The one argument-validation layer of the command line: argparse ``type=`` functions and checks.

Every command declares its numbers and paths through these, so an absurd argument (a negative
count, NaN, a window of 10^8 samples, a 37-bit CAN id, an output path in a missing directory) is
refused at argument time with exit code 2 and one clear line, before any work is done. Only the
standard library is imported here: ``mkc-stream --help`` stays fast.
"""
from __future__ import annotations

import argparse
import math
import os
import stat

#: largest standard (11-bit) and extended (29-bit) CAN arbitration ids
CAN_STD_MAX, CAN_EXT_MAX = 0x7FF, 0x1FFFFFFF
#: smallest window the streaming calibrator accepts (the largest is mkc_stream.state.MAX_WINDOW)
MIN_WINDOW = 16


def _err(msg):
    return argparse.ArgumentTypeError(msg)


def _int(text) -> int:
    try:
        return int(str(text).strip(), 0)
    except ValueError:
        raise _err(f"{text!r} is not an integer") from None


def _float(text) -> float:
    try:
        return float(text)
    except ValueError:
        raise _err(f"{text!r} is not a number") from None


def int_range(lo: int | None = None, hi: int | None = None, what: str = ""):
    """An integer in [lo, hi] (either end open when None); decimal or 0x...."""
    def parse(text):
        v = _int(text)
        if lo is not None and v < lo:
            raise _err(f"{v} is less than {lo}{what}")
        if hi is not None and v > hi:
            raise _err(f"{v} is more than {hi}{what}")
        return v
    parse.__name__ = "integer"        # argparse names the type in its own messages
    return parse


positive_int = int_range(1)
nonneg_int = int_range(0)


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open=False, hi_open=False,
                allow_inf=False):
    """A finite float in the range (NaN never; inf only with ``allow_inf``)."""
    def parse(text):
        v = _float(text)
        if math.isnan(v) or (math.isinf(v) and not allow_inf):
            raise _err(f"{text!r} is not a finite number")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise _err(f"{v:g} must be {'>' if lo_open else '>='} {lo:g}")
        if hi is not None and (v > hi or (hi_open and v == hi)):
            raise _err(f"{v:g} must be {'<' if hi_open else '<='} {hi:g}")
        return v
    parse.__name__ = "number"
    return parse


finite_float = float_range()
positive_float = float_range(0.0, lo_open=True)
nonneg_float = float_range(0.0)
fraction = float_range(0.0, 1.0)


def window_size(text) -> int:
    """Samples in a streaming window: MIN_WINDOW .. mkc_stream.state.MAX_WINDOW (memory and time
    grow with it: 10^8 samples took 20 GB before it was refused)."""
    from ..state import MAX_WINDOW      # numpy/numba: only when a window is actually given

    v = _int(text)
    if not MIN_WINDOW <= v <= MAX_WINDOW:
        raise _err(f"{v} is outside {MIN_WINDOW}..{MAX_WINDOW} samples")
    return v


window_size.__name__ = "window"


def can_id(text) -> int:
    """A CAN arbitration id: standard 11-bit (<= 0x7FF) or extended 29-bit (<= 0x1FFFFFFF)."""
    v = _int(text)
    if not 0 <= v <= CAN_EXT_MAX:
        raise _err(f"{text} is not a CAN id (standard 11-bit ids go to 0x7FF, extended 29-bit ones to 0x1FFFFFFF)")
    return v


can_id.__name__ = "CAN id"


def vector3(text) -> tuple[float, float, float]:
    """Three finite numbers x,y,z."""
    parts = [p for p in str(text).split(",")]
    if len(parts) != 3:
        raise _err(f"{text!r} is not three numbers x,y,z")
    return tuple(finite_float(p) for p in parts)


vector3.__name__ = "x,y,z"


def _check_writable_file(path: str) -> None:
    if os.path.isdir(path):
        raise _err(f"{path} is a directory")
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise _err(f"cannot write {path}: directory {parent} does not exist")
    if os.path.exists(path):
        if not os.access(path, os.W_OK):
            raise _err(f"cannot write {path}: permission denied")
    elif not os.access(parent, os.W_OK | os.X_OK):
        raise _err(f"cannot write {path}: directory {parent} is not writable")


def writable_path(text) -> str:
    """An output file that can be written (its directory exists and is writable); not created here."""
    _check_writable_file(text)
    return text


writable_path.__name__ = "output path"


def json_dest(text) -> str:
    """``-`` (stdout) or a writable file."""
    return text if text == "-" else writable_path(text)


json_dest.__name__ = "output path"


def writable_dir(text) -> str:
    """A directory to write into: an existing writable one, or one that can be created."""
    path = os.path.abspath(text)
    probe = path
    while not os.path.exists(probe):
        up = os.path.dirname(probe)
        if up == probe:
            break
        probe = up
    if not os.path.isdir(probe):
        raise _err(f"cannot write into {text}: {probe} is not a directory")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise _err(f"cannot write into {text}: {probe} is not writable")
    return text


writable_dir.__name__ = "directory"


def input_file(text) -> str:
    """A file to read: refuse directories and devices (reading /dev/zero never ends) at argument
    time; a missing file is left to the reader, whose message names it. FIFOs (``<(zcat ...)``)
    and ``demo`` pass."""
    try:
        st = os.stat(text)
    except OSError:
        return text
    if stat.S_ISDIR(st.st_mode):
        raise _err(f"{text} is a directory, not a recording")
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
        raise _err(f"{text} is a device, not a recording")
    return text


input_file.__name__ = "input file"


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(os.path.realpath(a)) == os.path.abspath(os.path.realpath(b))


def check_new_output(path: str | None, force: bool, inputs=(), flag: str = "--out") -> None:
    """A recording output must not be one of the inputs (never, even with --force: it would be
    truncated before it is read) and must not replace an existing file unless ``force``.
    Raises mkc_stream.commands.common.UsageError."""
    from .common import UsageError

    if not path:
        return
    for src in inputs:
        if src and os.path.exists(src) and _same_file(path, src):
            raise UsageError(f"{flag} {path} is the input file {src}; it would be overwritten while it is read")
    if os.path.lexists(path) and not force and not _is_special(path):
        raise UsageError(f"{flag} {path} already exists; give --force to overwrite it")


def _is_special(path: str) -> bool:
    """/dev/null and friends: writing there replaces nothing."""
    try:
        return not stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def params_dest(text) -> tuple:
    """TARGET:PATH for --params: a parameter-file target (mkc_stream.params.TARGETS) and a writable file."""
    target, sep, path = text.partition(":")
    targets = ("ardupilot", "px4", "ros", "c")
    if not sep or target not in targets or not path:
        raise argparse.ArgumentTypeError(f"expected TARGET:PATH with TARGET one of {', '.join(targets)}; got {text!r}")
    return target, writable_path(path)


params_dest.__name__ = "parameter file"
