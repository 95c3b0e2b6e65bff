"""mkc-stream command line: one verb per subcommand, heavy imports inside the subcommand.

Exit codes: 0 ok/accepted, 1 rejected or mismatch, 2 usage or unreadable input.
"""
from __future__ import annotations

import argparse
import json
import sys

EXIT_OK, EXIT_REJECTED, EXIT_USAGE = 0, 1, 2


class UsageError(Exception):
    """A problem with the user's input: printed as one clear line, exit code 2."""


def _write_json(obj, dest):
    text = json.dumps(obj, indent=2, allow_nan=False)
    if dest == "-":
        sys.stdout.write(text + "\n")
    else:
        with open(dest, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")


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


def cmd_calibrate(args) -> int:
    import numpy as np

    from .calib.acceptance import check
    from .calib.ellipsoid import EllipsoidError
    from .calib.fit import fit_ellipsoid, make_estimator
    from .io.recording import RecordingError, read_recording

    try:
        rec = read_recording(args.recording)
    except (OSError, RecordingError) as exc:
        raise UsageError(f"cannot read {args.recording}: {exc}") from exc
    unit = rec.mag_unit
    counts = rec.counts()
    make_estimator(args.method)          # unknown method -> usage error before any work
    fit, reason = None, ""
    try:
        fit = fit_ellipsoid(rec.mag, args.method)
        accepted, reason = check(fit.quality, fit.field, unit)
    except EllipsoidError as exc:
        accepted, reason = False, str(exc)
    if not args.quiet:
        _report(args.recording, rec, fit, accepted, reason, unit, sys.stderr if args.json == "-" else sys.stdout)
    if args.plot and fit is not None:
        from .plots import plot_calibration

        plot_calibration(rec.mag, fit, args.plot, title=str(args.recording))
    if args.json:
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
        _write_json(obj, args.json)
    return EXIT_OK if accepted else EXIT_REJECTED


def cmd_methods(args) -> int:
    from .calib.fit import available_methods

    for name in available_methods():
        print(name)
    return EXIT_OK


def cmd_demo_path(args) -> int:
    from .io.recording import bundled_recording_path

    print(bundled_recording_path())
    return EXIT_OK


def build_parser():
    p = argparse.ArgumentParser(prog="mkc-stream", description="Robust live IMU calibration (MKC-EM).")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    c = sub.add_parser("calibrate", help="calibrate a magnetometer recording (batch)")
    c.add_argument("recording", help="recording CSV (spec/recording.md), .csv or .csv.gz; 'demo' for the bundled one")
    c.add_argument("--method", default="mkc-em", help="mkc-em (default), mkc, ls, or a baseline (see `mkc-stream methods`)")
    c.add_argument("--json", metavar="PATH", help="write the machine-readable result ('-' for stdout)")
    c.add_argument("--plot", metavar="PNG", help="save a plot of the fit (needs the [plot] extra)")
    c.add_argument("--quiet", action="store_true", help="no human report")
    c.set_defaults(func=cmd_calibrate)

    m = sub.add_parser("methods", help="list the calibration methods")
    m.set_defaults(func=cmd_methods)

    d = sub.add_parser("demo-path", help="print the path of the bundled real recording")
    d.set_defaults(func=cmd_demo_path)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    if getattr(args, "recording", None) == "demo":
        from .io.recording import bundled_recording_path

        args.recording = str(bundled_recording_path())
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"mkc-stream: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ImportError as exc:
        print(f"mkc-stream: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("mkc-stream: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - an MKCInputError etc. is the user's input
        from ._validation import MKCInputError

        if isinstance(exc, MKCInputError):
            print(f"mkc-stream: error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        raise


if __name__ == "__main__":
    sys.exit(main())
