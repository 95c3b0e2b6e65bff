"""What every command shares, below both the commands and :mod:`mkc_stream.cli`: the exit codes,
UsageError, writing results (write_json, Outputs), progress lines, reading a recording, and the
options several commands declare (--json, --quiet, --window / --estep-every).

Only the standard library (and :mod:`mkc_stream.jsonout`) at import time: ``mkc-stream --help``
stays fast; numpy and the calibrator are imported inside the functions that need them.
"""
from __future__ import annotations

import json
import sys
import time

from ..defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from ..jsonout import jsonable

EXIT_OK, EXIT_REJECTED, EXIT_USAGE = 0, 1, 2
EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 130, 141


class UsageError(Exception):
    """A problem with the user's input: printed as one clear line, exit code 2."""


class OutputError(UsageError):
    """A result file could not be written (the result itself went to stdout): exit code 2."""


# ----------------------------------------------------------------------------------------------
# shared options
# ----------------------------------------------------------------------------------------------

def add_json_option(p, what="the machine-readable result"):
    """--json PATH: where the command's JSON goes ('-' for stdout)."""
    from .argtypes import json_dest

    p.add_argument("--json", metavar="PATH", type=json_dest, help=f"write {what} ('-' for stdout)")


def add_quiet_option(p, help="no human report"):
    p.add_argument("--quiet", action="store_true", help=help)


def add_window_options(p, window_help="samples kept in the window (default 512, at most 65536)", when=""):
    """--window and --estep-every of the streaming calibrator; ``when`` prefixes both helps (e.g. "--stream: ")."""
    from .argtypes import positive_int, window_size

    p.add_argument("--window", type=window_size, default=DEFAULT_WINDOW, help=when + window_help)
    p.add_argument("--estep-every", type=positive_int, default=DEFAULT_ESTEP_EVERY,
                   help=f"{when}E-step every K samples (default {DEFAULT_ESTEP_EVERY})")


# ----------------------------------------------------------------------------------------------
# results and reports
# ----------------------------------------------------------------------------------------------

def write_json(obj, dest):
    """Write the result; if the file cannot be written, print it to stdout and raise OutputError,
    so a run's result is never lost (the destination was checked before the work, but a disk can
    fill or a directory vanish meanwhile)."""
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False) + "\n"
    if dest == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    try:
        with open(dest, "w", encoding="utf-8") as fh:
            fh.write(text)
    except BrokenPipeError:
        raise
    except OSError as exc:
        sys.stdout.write(text)
        sys.stdout.flush()
        raise OutputError(f"cannot write {dest}: {exc.strerror or exc}; the result was printed to stdout "
                          "instead") from None


class Outputs:
    """The result files of a command, written after the work: one failing does not stop the others,
    and the failures are raised together at the end (exit code 2)."""

    def __init__(self):
        self.failed: list[str] = []

    def attempt(self, what, fn, *args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except BrokenPipeError:
            raise
        except OutputError as exc:
            self.failed.append(str(exc))
        except OSError as exc:
            self.failed.append(f"cannot write {what}: {exc.strerror or exc}")
        return None

    def done(self, code: int) -> int:
        if self.failed:
            raise OutputError("; ".join(self.failed))
        return code


class Progress:
    """Progress of a long job on stderr: a live line on a terminal once the job has run for
    ``tty_after_s``; otherwise (a log, CI) a plain line every ``every_s`` seconds, so a long run is
    never silent."""

    EVERY_S = 10.0

    def __init__(self, enabled=True, every_s=None, tty_after_s=1.0, clock=time.monotonic, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = self.EVERY_S if every_s is None else every_s
        self.tty_after_s, self.clock = tty_after_s, clock
        self.t0 = self.last = clock()
        self.shown = False

    def __call__(self, text: str):
        if not self.enabled:
            return
        now = self.clock()
        if self.tty:
            if now - self.t0 < self.tty_after_s:
                return
            self.stream.write("\r" + text)
        elif now - self.last >= self.every_s:
            self.stream.write(f"{text} ({now - self.t0:.0f} s)\n")
            self.last = now
        else:
            return
        self.shown = True
        self.stream.flush()

    def end(self):
        if self.enabled and self.tty and self.shown:
            self.stream.write("\n")
            self.stream.flush()


def fmt_vec(v, unit):
    """Three numbers of a report line: ``[ x, y, z ] unit``."""
    return "[" + ", ".join(f"{x:10.4g}" for x in v) + f" ] {unit}"


# ----------------------------------------------------------------------------------------------
# inputs and the calibrator
# ----------------------------------------------------------------------------------------------

def load_recording(path):
    """read_recording (or, for a flight log, ``read_flight_log``: ``LOG#instance=ID`` chooses the
    stream), with every way a file can fail to be a recording mapped to a UsageError."""
    from ..ingest.flightlogs import is_flight_log, read_flight_log
    from ..io.recording import read_recording

    try:
        if is_flight_log(path):
            return read_flight_log(path)
        return read_recording(path)
    except (OSError, ValueError) as exc:        # RecordingError is a ValueError
        raise UsageError(f"cannot read {path}: {exc}") from None
    except MemoryError:
        raise UsageError(f"cannot read {path}: it does not fit in memory") from None


def check_plot_extra(plot):
    """--plot needs matplotlib: say so before the work, not after it."""
    import importlib.util

    if plot and importlib.util.find_spec("matplotlib") is None:
        raise UsageError("--plot needs matplotlib: pip install 'mkc-stream[plot]'")


def compiled_calibrator(window, estep_every, unit="uT", **kwargs):
    """A fresh MagCalibrator whose kernels are already compiled: a small calibrator runs a noisy
    sphere swept twice through its window first (numba compiles per type, not per size, so a
    256-sample window compiles everything a 65536-sample one needs, at a fraction of the cost)."""
    import numpy as np

    from ..calib.streaming import MagCalibrator

    w = min(window, 256)
    warm = MagCalibrator(window=w, estep_every=min(estep_every, w), unit=unit, keep_history=False)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(2 * w + 64, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    warm.learn_many(50.0 * u + np.array([10.0, -5.0, 3.0]) + 0.1 * rng.normal(size=u.shape))
    return MagCalibrator(window=window, estep_every=estep_every, unit=unit, **kwargs)
