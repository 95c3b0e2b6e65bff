"""mkc-stream command line: one verb per subcommand, heavy imports inside the subcommand.

Exit codes: 0 ok/accepted, 1 rejected or mismatch, 2 usage error, unreadable input or a result
that could not be written (it is then printed to stdout instead), 130 interrupted, 141 output pipe
closed early (``mkc-stream ... | head -1``: quiet, as a process ended by SIGPIPE).
Arguments are checked before any work by the ``type=`` functions of :mod:`.commands.argtypes`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
import time

from .jsonout import jsonable  # noqa: F401  (re-exported: the one JSON cleaner)

EXIT_OK, EXIT_REJECTED, EXIT_USAGE = 0, 1, 2
EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 130, 141


class UsageError(Exception):
    """A problem with the user's input: printed as one clear line, exit code 2."""


class OutputError(UsageError):
    """A result file could not be written (the result itself went to stdout): exit code 2."""


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


def _fmt_vec(v, unit):
    return "[" + ", ".join(f"{x:10.4g}" for x in v) + f" ] {unit}"


def _report(path, rec, fit, accepted, reason, unit, out):
    c = rec.counts()
    p = lambda s="": print(s, file=out)  # noqa: E731
    p(f"mkc-stream calibrate: {path}")
    p(f"  read          : {c['samples']} samples, {c['bad_frames']} bad rows skipped, {c['gaps']} time gaps")
    if rec.bad_rows:
        shown = ", ".join(f"line {ln} ({why})" for ln, why in rec.bad_rows[:3])
        more = f" and {len(rec.bad_rows) - 3} more" if len(rec.bad_rows) > 3 else ""
        p(f"  bad rows      : {shown}{more}")
    if fit is None:
        p(f"  status        : REJECTED - {reason}")
        return
    p(f"  method        : {fit.method}")
    p(f"  hard iron b   : {_fmt_vec(fit.hard_iron, unit)}")
    S = fit.soft_iron
    p(f"  soft iron S   : {_fmt_vec(S[0], '')}")
    p(f"                  {_fmt_vec(S[1], '')}")
    p(f"                  {_fmt_vec(S[2], '')}   (m_cal = S (m_raw - b), det S = 1)")
    p(f"  field F       : {fit.field:.5g} {unit}")
    if fit.channels:
        ch = fit.channels[0]
        est = fit.estimator
        extra = f", {est.n_iter_} EM rounds" if getattr(est, "em", False) else ""
        p(f"  kernel        : sigma {ch['sigma']:.4g}, d {ch['d']:.4g}{extra}")
    q = fit.quality
    p(f"  quality       : inlier residual rms {q['residual_rms']:.4g} {unit} ({q['residual_rms'] / fit.field:.2%} of F), "
      f"norm spread {q['norm_spread_inliers']:.2%} (inliers) / {q['norm_spread']:.2%} (all)")
    p(f"                  sphere coverage {q['coverage']:.0%}, outliers {q['outlier_fraction']:.1%}, "
      f"condition {q['condition']:.3g}")
    p(f"  status        : {'ACCEPTED' if accepted else 'REJECTED - ' + reason}")


def load_recording(path):
    """read_recording, with every way a file can fail to be a recording mapped to a UsageError."""
    from .io.recording import read_recording

    try:
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


def cmd_calibrate(args) -> int:

    from .calib.acceptance import check
    from .calib.ellipsoid import EllipsoidError
    from .calib.fit import fit_ellipsoid, make_estimator

    if not args.stream:
        make_estimator(args.method)          # unknown method -> usage error before any work
    check_plot_extra(args.plot)
    rec = load_recording(args.recording)
    unit = rec.mag_unit
    counts = rec.counts()
    outputs = Outputs()
    if args.stream:
        obj, accepted = _stream_calibrate(args, rec, unit, counts, sys.stderr if args.json == "-" else sys.stdout)
        if args.json:
            obj["recording"] = str(args.recording)
            outputs.attempt(args.json, write_json, obj, args.json)
        return outputs.done(EXIT_OK if accepted else EXIT_REJECTED)
    fit, reason = None, ""
    try:
        fit = fit_ellipsoid(rec.mag, args.method)
        accepted, reason = check(fit.quality, fit.field, unit)
    except EllipsoidError as exc:
        accepted, reason = False, str(exc)
    if not args.quiet:
        _report(args.recording, rec, fit, accepted, reason, unit, sys.stderr if args.json == "-" else sys.stdout)
    if args.json:             # the result first: a plot that fails cannot take it with it
        if fit is None:
            obj = {"hard_iron": None, "soft_iron": None, "field": None, "channels": [],
                   "quality": {"residual_rms": None, "coverage": None, "outlier_fraction": None, "condition": None},
                   "status": "rejected", "reason": reason, "counts": counts, "method": args.method}
        else:
            obj = fit.to_json(counts=counts, status="accepted" if accepted else "rejected",
                              reason=None if accepted else reason)
            obj["units"] = {"mag": unit}
            obj["n_iter"] = int(getattr(fit.estimator, "n_iter_", 0) or 0)
        obj["recording"] = str(args.recording)
        outputs.attempt(args.json, write_json, obj, args.json)
    if args.plot and fit is not None:
        from .plots import plot_calibration

        outputs.attempt(args.plot, plot_calibration, rec.mag, fit, args.plot, title=str(args.recording))
    return outputs.done(EXIT_OK if accepted else EXIT_REJECTED)


def compiled_calibrator(window, estep_every, unit="uT", **kwargs):
    """A fresh MagCalibrator whose kernels are already compiled: a small calibrator runs a noisy
    sphere swept twice through its window first (numba compiles per type, not per size, so a
    256-sample window compiles everything a 65536-sample one needs, at a fraction of the cost)."""
    import numpy as np

    from .calib.streaming import MagCalibrator

    w = min(window, 256)
    warm = MagCalibrator(window=w, estep_every=min(estep_every, w), unit=unit, keep_history=False)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(2 * w + 64, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    warm.update(50.0 * u + np.array([10.0, -5.0, 3.0]) + 0.1 * rng.normal(size=u.shape))
    return MagCalibrator(window=window, estep_every=estep_every, unit=unit, **kwargs)


def _stream_calibrate(args, rec, unit, counts, out):
    """Replay a recording through the streaming calibrator; returns (json_obj, accepted)."""
    cal = compiled_calibrator(args.window, args.estep_every, unit)
    N = len(rec.mag)
    chunk = max(1000, N // 50)
    t0 = time.perf_counter()
    progress = Progress(enabled=not args.quiet)
    for start in range(0, N, chunk):
        cal.update(rec.mag[start:start + chunk])
        done = min(N, start + chunk)
        state = "accepted" if cal.accepted is not None else cal.status_reason()[:50]
        progress(f"  streaming {done}/{N} samples ({done / N:.0%}), {state}")
    progress.end()
    elapsed = time.perf_counter() - t0
    evolution = [{"samples": ev.samples_seen, "accepted": ev.accepted,
                  "hard_iron": None if ev.hard_iron is None else [float(v) for v in ev.hard_iron],
                  "field": None if ev.field is None else float(ev.field),
                  "coverage": ev.coverage, "reason": ev.reason or None} for ev in cal.history]
    counts = dict(counts)
    counts["bad_frames"] += cal.counts()["bad_frames"]
    acc = cal.accepted
    if acc is None:
        obj = {"hard_iron": None, "soft_iron": None, "field": None, "channels": [],
               "quality": {"residual_rms": None, "coverage": None, "outlier_fraction": None, "condition": None},
               "status": "rejected", "reason": cal.status_reason(), "counts": counts}
    else:
        obj = acc.to_json(counts=counts)
    obj.update({"method": "mkc-em-stream", "window": args.window, "estep_every": args.estep_every,
                "first_accepted_at_sample": cal.first_accepted_at, "evolution": evolution,
                "samples_per_second": N / elapsed if elapsed > 0 else None, "units": {"mag": unit}})
    if not args.quiet:
        p = lambda x="": print(x, file=out)  # noqa: E731
        p(f"mkc-stream calibrate --stream: {args.recording}")
        p(f"  read          : {counts['samples']} samples, {counts['bad_frames']} bad, window {args.window}, "
          f"E-step every {args.estep_every}; {N / elapsed:,.0f} samples/s")
        step = max(1, len(evolution) // 12)
        p("  evolution     : samples   accepted  hard iron                         field   coverage")
        for ev in evolution[::step] + ([evolution[-1]] if evolution and (len(evolution) - 1) % step else []):
            hi = "-" if ev["hard_iron"] is None else "[" + ", ".join(f"{v:9.4g}" for v in ev["hard_iron"]) + "]"
            fld = "-" if ev["field"] is None else f"{ev['field']:.4g}"
            cov = "-" if ev["coverage"] is None else f"{ev['coverage']:.0%}"
            p(f"                  {ev['samples']:8d}  {'yes' if ev['accepted'] else 'no ':3s}       {hi:33s} {fld:7s} {cov}")
        if acc is None:
            p(f"  status        : REJECTED - {cal.status_reason()}")
        else:
            p(f"  first accepted: after {cal.first_accepted_at} samples")
            p(f"  hard iron b   : {_fmt_vec(acc.hard_iron, unit)}")
            for i, row in enumerate(acc.soft_iron):
                p(("  soft iron S   : " if i == 0 else "                  ") + _fmt_vec(row, ""))
            p(f"  field F       : {acc.field:.5g} {unit}")
            p(f"  kernel        : sigma {acc.sigma:.4g}, d {acc.d:.4g}")
            q = acc.quality
            p(f"  quality       : inlier residual rms {q['residual_rms']:.4g} {unit}, coverage {q['coverage']:.0%}, "
              f"outliers {q['outlier_fraction']:.1%}, condition {q['condition']:.3g}")
            p("  status        : ACCEPTED")
    return obj, acc is not None


def cmd_methods(args) -> int:
    from .calib.fit import available_methods

    for name in available_methods():
        print(name)
    return EXIT_OK


def cmd_demo_path(args) -> int:
    from .io.recording import bundled_recording_path

    print(bundled_recording_path())
    return EXIT_OK


class _Parser(argparse.ArgumentParser):
    """argparse with the contract's one-line error (its subcommand parsers are of this class too)."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"mkc-stream: error: {message} (see {self.prog} --help)\n")


def build_parser():
    from .commands.argtypes import input_file, json_dest, positive_int, window_size, writable_path

    p = _Parser(prog="mkc-stream", description="Robust live IMU calibration (MKC-EM).",
                                epilog="Exit codes: 0 accepted/ok, 1 rejected or mismatch, 2 usage error, unreadable "
                                       "input or unwritable result, 130 interrupted, 141 output pipe closed.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    c = sub.add_parser("calibrate", help="calibrate a magnetometer recording (batch)")
    c.add_argument("recording", type=input_file,
                   help="recording CSV (docs/spec/recording.md), .csv or .csv.gz; 'demo' for the bundled one")
    c.add_argument("--method", default="mkc-em", help="mkc-em (default), mkc, ls, or a baseline (see `mkc-stream methods`)")
    c.add_argument("--json", metavar="PATH", type=json_dest, help="write the machine-readable result ('-' for stdout)")
    c.add_argument("--plot", metavar="PNG", type=writable_path, help="save a plot of the fit (needs the [plot] extra)")
    c.add_argument("--quiet", action="store_true", help="no human report and no progress")
    c.add_argument("--stream", action="store_true", help="replay through the streaming calibrator (MKC-EM on a window)")
    c.add_argument("--window", type=window_size, default=512,
                   help="--stream: samples kept in the window (default 512, at most 65536)")
    c.add_argument("--estep-every", type=positive_int, default=32, help="--stream: E-step every K samples (default 32)")
    c.set_defaults(func=cmd_calibrate)

    m = sub.add_parser("methods", help="list the calibration methods")
    m.set_defaults(func=cmd_methods)

    d = sub.add_parser("demo-path", help="print the path of the bundled real recording")
    d.set_defaults(func=cmd_demo_path)

    import importlib

    from .commands import COMMAND_MODULES

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
