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


def write_json(obj, dest):
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
    if args.stream:
        if args.window < 16 or args.estep_every < 1:
            raise UsageError("--window must be >= 16 and --estep-every >= 1")
        obj, accepted = _stream_calibrate(args, rec, unit, counts, sys.stderr if args.json == "-" else sys.stdout)
        if args.json:
            obj["recording"] = str(args.recording)
            write_json(obj, args.json)
        return EXIT_OK if accepted else EXIT_REJECTED
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
        write_json(obj, args.json)
    return EXIT_OK if accepted else EXIT_REJECTED


def _stream_calibrate(args, rec, unit, counts, out):
    """Replay a recording through the streaming calibrator; returns (json_obj, accepted)."""
    import time


    from .calib.streaming import MagCalibrator

    cal = MagCalibrator(window=args.window, estep_every=args.estep_every, unit=unit)
    cal.update(rec.mag[: min(len(rec.mag), 2 * args.window)])          # compiles the kernels
    cal.reset()
    N = len(rec.mag)
    chunk = max(1000, N // 50)
    t0 = time.perf_counter()
    show = (N > 20 * chunk or N > 50_000) and sys.stderr.isatty()
    for start in range(0, N, chunk):
        cal.update(rec.mag[start:start + chunk])
        if show and not args.quiet:
            done = min(N, start + chunk)
            state = "accepted" if cal.accepted is not None else cal.status_reason()[:50]
            print(f"\r  streaming {done}/{N} samples ({done / N:.0%}), {state}", end="", file=sys.stderr, flush=True)
    if show and not args.quiet:
        print("", file=sys.stderr)
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


def build_parser():
    p = argparse.ArgumentParser(prog="mkc-stream", description="Robust live IMU calibration (MKC-EM).")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    c = sub.add_parser("calibrate", help="calibrate a magnetometer recording (batch)")
    c.add_argument("recording", help="recording CSV (spec/recording.md), .csv or .csv.gz; 'demo' for the bundled one")
    c.add_argument("--method", default="mkc-em", help="mkc-em (default), mkc, ls, or a baseline (see `mkc-stream methods`)")
    c.add_argument("--json", metavar="PATH", help="write the machine-readable result ('-' for stdout)")
    c.add_argument("--plot", metavar="PNG", help="save a plot of the fit (needs the [plot] extra)")
    c.add_argument("--quiet", action="store_true", help="no human report")
    c.add_argument("--stream", action="store_true", help="replay through the streaming calibrator (MKC-EM on a window)")
    c.add_argument("--window", type=int, default=512, help="--stream: samples kept in the window (default 512)")
    c.add_argument("--estep-every", type=int, default=32, help="--stream: E-step every K samples (default 32)")
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
