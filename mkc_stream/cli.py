"""mkc-stream command line: builds the parser, registers the commands, runs the top-level handler.

Every command lives in :mod:`mkc_stream.commands` (one module per group, listed in COMMAND_MODULES);
what they share (exit codes, UsageError, write_json, the common options) is in
:mod:`mkc_stream.commands.common`, below both. Heavy imports happen inside the commands.

Exit codes: 0 ok/accepted, 1 rejected or mismatch, 2 usage error, unreadable input or a result
that could not be written (it is then printed to stdout instead), 130 interrupted, 141 output pipe
closed early (``mkc-stream ... | head -1``: quiet, as a process ended by SIGPIPE).
Arguments are checked before any work by the ``type=`` functions of :mod:`.commands.argtypes`.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings

from .commands.common import EXIT_BROKEN_PIPE, EXIT_INTERRUPTED, EXIT_USAGE, UsageError


class _Parser(argparse.ArgumentParser):
    """argparse with the contract's one-line error (its subcommand parsers are of this class too)."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"mkc-stream: error: {message} (see {self.prog} --help)\n")


def build_parser():
    import importlib

    from .commands import COMMAND_MODULES

    p = _Parser(prog="mkc-stream", description="Robust live IMU calibration (MKC-EM).",
                epilog="Exit codes: 0 accepted/ok, 1 rejected or mismatch, 2 usage error, unreadable "
                       "input or unwritable result, 130 interrupted, 141 output pipe closed.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return p


def _error(msg) -> int:
    print(f"mkc-stream: error: {msg}", file=sys.stderr)
    return EXIT_USAGE


def _quiet_broken_pipe() -> int:
    """The reader of stdout went away (``| head -1``): stop quietly. stdout is pointed at /dev/null
    so the interpreter's final flush does not print a second error."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):   # not a real file (a test's capture)
        pass
    return EXIT_BROKEN_PIPE


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings about the user's input (a reader's RecordingWarning) as one line in the tool's voice;
    any other warning keeps Python's format (it is for a developer)."""
    from .io.recording import RecordingWarning

    if issubclass(category, RecordingWarning):
        print(f"mkc-stream: warning: {message}", file=sys.stderr if file is None else file)
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def main(argv=None) -> int:
    """The exit-code contract in one place (module docstring); returns the code, never raises for
    the user's input or environment (argparse's own exits included)."""
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except SystemExit as exc:                  # argparse: --help (0) or a refused argument (2)
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    if getattr(args, "recording", None) == "demo":
        from .io.recording import bundled_recording_path

        args.recording = str(bundled_recording_path())
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            code = args.func(args)
        sys.stdout.flush()           # a closed pipe shows here, not in the interpreter's exit
        return code
    except UsageError as exc:
        return _error(exc)
    except ImportError as exc:
        return _error(exc)
    except KeyboardInterrupt:
        print("mkc-stream: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return _quiet_broken_pipe()
    except MemoryError:
        return _error("out of memory; try a smaller input, --window or --max-samples")
    except OSError as exc:                    # a file or device the command could not use
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return _error(f"{where}{exc.strerror or exc}")
    except Exception as exc:  # noqa: BLE001 - an MKCInputError etc. is the user's input
        from ._validation import MKCInputError
        from .io.recording import RecordingError

        if isinstance(exc, (MKCInputError, RecordingError)):
            return _error(exc)
        raise


if __name__ == "__main__":
    sys.exit(main())
