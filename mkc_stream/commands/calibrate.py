"""`calibrate` (a recording, batch or --stream), `methods` (the calibration methods) and `demo-path`."""
from __future__ import annotations

import sys
import time

from .calreport import calibration_lines, status_line
from .flightcal import add_attitude_options, all_instances, attitude_calibrate, wants_attitude, write_flight_plots
from .common import (EXIT_OK, EXIT_REJECTED, Outputs, Progress, add_json_option, add_quiet_option, add_window_options,
                     check_plot_extra, compiled_calibrator, fmt_vec, load_recording, write_json)


def register(subparsers):
    from .argtypes import input_file, params_dest, writable_path

    c = subparsers.add_parser("calibrate", help="calibrate a magnetometer recording (batch)")
    c.add_argument("recording", type=input_file,
                   help="recording CSV (docs/spec/recording.md), .csv or .csv.gz; 'demo' for the bundled one")
    c.add_argument("--method", default="mkc-em-geo-dir",
                   help="mkc-em-geo-dir (default: the geometric MKC-EM with direction weighting), mkc-em-geo, "
                        "mkc-em (the paper's algebraic form), mkc, ls, or a baseline (see `mkc-stream methods`)")
    add_json_option(c)
    c.add_argument("--plot", metavar="PNG", type=writable_path, help="save a plot of the fit (needs the [plot] extra)")
    add_quiet_option(c, "no human report and no progress")
    c.add_argument("--stream", action="store_true",
                   help="replay through the streaming calibrator (MKC-EM on a window): the ellipsoid model, or for a "
                        "recording with an attitude and a position (or --lat/--lon, as --attitude) the attitude-aided "
                        "vector model in fixed memory (no delay search; docs/flight.md)")
    add_window_options(c, when="--stream: ")
    c.add_argument("--params", metavar="TARGET:PATH", type=params_dest, action="append", default=[],
                   help="also write the accepted calibration as parameters: ardupilot:FILE.param, "
                        "px4:FILE.params, ros:FILE.yaml or c:FILE.h (docs/params.md); repeatable")
    add_attitude_options(c)
    c.set_defaults(func=cmd_calibrate)

    m = subparsers.add_parser("methods", help="list the calibration methods")
    m.set_defaults(func=cmd_methods)

    d = subparsers.add_parser("demo-path", help="print the path of the bundled real recording")
    d.set_defaults(func=cmd_demo_path)


def _report(path, rec, fit, cal, rejection, unit, out):
    c = rec.counts()
    p = lambda s="": print(s, file=out)  # noqa: E731
    p(f"mkc-stream calibrate: {path}")
    p(f"  read          : {c['samples']} samples, {c['bad_frames']} bad rows skipped, {c['gaps']} time gaps")
    if rec.bad_rows:
        shown = ", ".join(f"line {ln} ({why})" for ln, why in rec.bad_rows[:3])
        more = f" and {len(rec.bad_rows) - 3} more" if len(rec.bad_rows) > 3 else ""
        p(f"  bad rows      : {shown}{more}")
    if cal is None:
        p(status_line(rejection))
        return
    est = fit.estimator
    note = f", {est.n_iter_} EM rounds" if getattr(est, "em", False) else ""
    for line in calibration_lines(cal, unit, kernel_note=note):
        p(line)


def cmd_calibrate(args) -> int:
    from ..calib.ellipsoid import EllipsoidError
    from ..calib.fit import fit_ellipsoid, make_estimator
    from ..calib.result import Rejection, no_calibration_json

    if not args.stream:
        make_estimator(args.method)          # unknown method -> usage error before any work
    check_plot_extra(args.plot)
    if args.all_instances:
        outputs = Outputs()
        plots = []
        obj, ok, calibrations = all_instances(args, args.recording, None if args.quiet else
                                              (sys.stderr if args.json == "-" else sys.stdout), plots)
        _write_params(args, outputs, calibrations, None)
        if args.json:
            outputs.attempt(args.json, write_json, obj, args.json)
        write_flight_plots(outputs, plots, args.recording)
        return outputs.done(EXIT_OK if ok else EXIT_REJECTED)
    rec = load_recording(args.recording)
    unit = rec.mag_unit
    counts = rec.counts()
    outputs = Outputs()
    if not args.stream and wants_attitude(args, rec):
        plots = []
        obj, fc, lines = attitude_calibrate(args, rec, unit, counts, plots)
        if not args.quiet:
            out = sys.stderr if args.json == "-" else sys.stdout
            print(f"mkc-stream calibrate --attitude: {args.recording}", file=out)
            print(f"  read          : {counts['samples']} samples, {counts['bad_frames']} bad rows skipped", file=out)
            for line in lines:
                print(line, file=out)
        _write_params(args, outputs, fc, unit)
        if args.json:
            obj["units"] = {"mag": unit}
            obj["recording"] = str(args.recording)
            outputs.attempt(args.json, write_json, obj, args.json)
        write_flight_plots(outputs, plots, args.recording)
        return outputs.done(EXIT_OK if fc is not None else EXIT_REJECTED)
    if args.stream and wants_attitude(args, rec):
        obj, acc = _flight_stream_calibrate(args, rec, unit, counts, sys.stderr if args.json == "-" else sys.stdout)
        _write_params(args, outputs, acc, unit)
        if args.json:
            obj["recording"] = str(args.recording)
            outputs.attempt(args.json, write_json, obj, args.json)
        return outputs.done(EXIT_OK if acc is not None else EXIT_REJECTED)
    if args.stream:
        from .flightcal import QUAT

        fallback = None
        if args.attitude is None and all(c in rec.aux for c in QUAT):
            fallback = ("the recording has an attitude but no position: the ellipsoid stream; --lat/--lon for the "
                        "attitude-aided one")
            if not args.quiet:
                print(f"mkc-stream calibrate --stream: note: {fallback}", file=sys.stderr if args.json == "-" else sys.stdout)
        obj, acc = _stream_calibrate(args, rec, unit, counts, sys.stderr if args.json == "-" else sys.stdout)
        _write_params(args, outputs, acc, unit)
        if args.json:
            if fallback:
                obj["notes"] = [fallback]
            obj["recording"] = str(args.recording)
            outputs.attempt(args.json, write_json, obj, args.json)
        return outputs.done(EXIT_OK if acc is not None else EXIT_REJECTED)
    fit = cal = None
    try:
        fit = fit_ellipsoid(rec.mag, args.method)
        cal = fit.calibration(unit, raw=rec.mag)
        rejection = cal.rejection
    except EllipsoidError as exc:
        rejection = Rejection("not_ellipsoid", str(exc))
    if not args.quiet:
        _report(args.recording, rec, fit, cal, rejection, unit, sys.stderr if args.json == "-" else sys.stdout)
    if args.json:             # the result first: a plot that fails cannot take it with it
        if cal is None:
            obj = no_calibration_json(rejection, counts, method=args.method)
        else:
            obj = cal.to_json(counts=counts)
            obj["units"] = {"mag": unit}
            obj["n_iter"] = int(getattr(fit.estimator, "n_iter_", 0) or 0)
        obj["recording"] = str(args.recording)
        outputs.attempt(args.json, write_json, obj, args.json)
    _write_params(args, outputs, cal if rejection is None else None, unit)
    if args.plot and fit is not None:
        from ..plots import plot_calibration

        outputs.attempt(args.plot, plot_calibration, rec.mag, fit, args.plot, title=str(args.recording))
    return outputs.done(EXIT_OK if rejection is None else EXIT_REJECTED)


def _write_params(args, outputs, cal, unit):
    """--params: the accepted calibration as each requested target's file (its note on stderr)."""
    if not args.params:
        return
    if not cal:
        print("mkc-stream calibrate: no accepted calibration, no parameter file written", file=sys.stderr)
        return
    from ..params import CalibrationValues, write_params

    try:                                # a flight calibration also carries its power compensation
        if isinstance(cal, list):       # --all-instances: [(instance, FlightCalibration)], one file for all
            values = [CalibrationValues(c.hard_iron, c.soft_iron, c.field, unit=c.unit, current_coeff=c.current,
                                        throttle_coeff=c.throttle, instance=k) for k, c in cal]
        else:
            values = CalibrationValues(cal.hard_iron, cal.soft_iron, cal.field, unit=unit,
                                       current_coeff=getattr(cal, "current", None),
                                       throttle_coeff=getattr(cal, "throttle", None))
    except ValueError as exc:           # counts: the targets need a physical unit
        outputs.failed.append(f"no parameter file written: {exc}")
        return
    for target, path in args.params:
        outputs.attempt(path, write_params, target, values, path)


def _replay(cal, N, feed, quiet) -> float:
    """feed(start, stop) for chunks of the N samples, with a progress line; returns the seconds taken."""
    chunk = max(1000, N // 50)
    t0 = time.perf_counter()
    progress = Progress(enabled=not quiet)
    for start in range(0, N, chunk):
        feed(start, min(N, start + chunk))
        done = min(N, start + chunk)
        state = "accepted" if cal.accepted is not None else cal.status_reason()[:50]
        progress(f"  streaming {done}/{N} samples ({done / N:.0%}), {state}")
    progress.end()
    return time.perf_counter() - t0


def _evolution(history, coverage: bool) -> list:
    """The JSON's "evolution": one entry per checkpoint (with the window's coverage when it has one)."""
    out = []
    for ev in history:
        e = {"samples": ev.samples_seen, "accepted": ev.accepted,
             "hard_iron": None if ev.hard_iron is None else [float(v) for v in ev.hard_iron],
             "field": None if ev.field is None else float(ev.field)}
        if coverage:
            e["coverage"] = ev.coverage
        e["reason"] = ev.reason or None
        out.append(e)
    return out


def _stream_calibrate(args, rec, unit, counts, out):
    """Replay a recording through the streaming calibrator; returns (json_obj, the accepted Calibration or None)."""
    from ..calib.result import no_calibration_json

    cal = compiled_calibrator(args.window, args.estep_every, unit)
    N = len(rec.mag)
    elapsed = _replay(cal, N, lambda a, b: cal.learn_many(rec.mag[a:b]), args.quiet)
    evolution = _evolution(cal.history, coverage=True)
    counts = dict(counts)
    counts["bad_frames"] += cal.counts()["bad_frames"]
    acc = cal.accepted
    if acc is None:
        obj = no_calibration_json(cal.status(), counts)
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
            p(status_line(cal.status()))
        else:
            for line in calibration_lines(acc, unit, first_accepted_at=cal.first_accepted_at):
                p(line)
    return obj, acc


def _flight_stream_calibrate(args, rec, unit, counts, out):
    """Replay a recording with attitude through the attitude-aided stream (flight/streaming.py); returns
    (json_obj, the accepted FlightStreamCalibration or None)."""
    from .._validation import MKCInputError
    from ..calib.result import Rejection, no_calibration_json
    from ..flight.streaming import recording_inputs
    from .common import UsageError

    method = "mkc-em-attitude-stream"
    if (args.lat is None) != (args.lon is None):
        raise UsageError("--lat and --lon go together")
    p = lambda x="": None if args.quiet else print(x, file=out)  # noqa: E731
    p(f"mkc-stream calibrate --stream --attitude: {args.recording}")
    try:
        cal, mag, q, power, notes = recording_inputs(rec, lat=args.lat, lon=args.lon, alt=args.alt, date=args.date,
                                                     yaw_only=args.yaw_only, window=args.window,
                                                     estep_every=args.estep_every)
    except (MKCInputError, ValueError, ImportError) as exc:
        rejection = Rejection("no_calibration", str(exc))
        p(f"  read          : {counts['samples']} samples, {counts['bad_frames']} bad rows skipped")
        p(status_line(rejection))
        return no_calibration_json(rejection, counts, method=method), None
    N = len(mag)
    elapsed = _replay(cal, N, lambda a, b: cal.learn_many(mag[a:b], q[a:b], None if power is None else power[a:b]),
                      args.quiet)
    evolution = _evolution(cal.history, coverage=False)
    counts = dict(counts)
    counts["bad_frames"] += cal.counts()["bad_frames"]
    acc = cal.accepted
    obj = no_calibration_json(cal.status(), counts) if acc is None else acc.to_json(counts=counts)
    obj.update({"method": method, "window": args.window, "estep_every": args.estep_every,
                "first_accepted_at_sample": cal.first_accepted_at, "evolution": evolution, "notes": notes,
                "samples_per_second": N / elapsed if elapsed > 0 else None, "units": {"mag": unit}})
    p(f"  read          : {counts['samples']} samples, {counts['bad_frames']} bad (non-finite field, attitude or "
      f"power), window {args.window}, E-step every {args.estep_every}; {N / elapsed:,.0f} samples/s")
    if acc is None:
        p(status_line(cal.status()))
    else:
        for line in _flight_stream_lines(acc, unit, cal.first_accepted_at, notes):
            p(line)
    return obj, acc


def _flight_stream_lines(acc, unit, first_accepted_at, notes) -> list:
    """The human report of an accepted attitude-aided stream calibration."""
    S = acc.soft_iron
    lines = ["  method        : mkc-em-attitude-stream (vector model against the Earth field, the log's attitude, "
             "fixed memory)",
             f"  hard iron b   : {fmt_vec(acc.hard_iron, unit)}"
             + ("" if not acc.uncertainty else f"  (sd {fmt_vec(acc.uncertainty['hard_iron_sd'], unit)}, one window)"),
             f"  soft iron S   : {fmt_vec(S[0], '')}", f"                  {fmt_vec(S[1], '')}",
             f"                  {fmt_vec(S[2], '')}   (m_cal = S (m_raw - b - K c), det S = 1)",
             f"  field F       : {acc.field:.5g} {unit}"]
    e = acc.earth
    if e is not None:
        lines.append(f"  Earth field   : {e.model}: {e.intensity_uT:.2f} uT, inclination {e.inclination_deg:.2f} deg, "
                     f"declination {e.declination_deg:.2f} deg; fitted gain {acc.scale:.4f} {unit} per uT")
    for name, k in acc.power.items():
        per = "/A" if name == "current" else " at full throttle"
        ci = acc.power_ci.get(name)
        ci_txt = "" if ci is None else "  95%: " + ", ".join(f"[{a:.3g}, {b:.3g}]" for a, b in ci)
        lines.append(f"  {name:<14s}: {fmt_vec(k, unit + per)}{ci_txt}")
    lines.append(f"  misalignment  : {fmt_vec(acc.misalignment_deg, 'deg')} (rotation vector, sensor to attitude frame)")
    lines.append(f"  pool          : {acc.pooled} checkpoints pooled; first accepted at sample {first_accepted_at}")
    if acc.held:
        lines.append(f"  held          : {', '.join(acc.held)} (chosen, not tested: the stream has no observability test)")
    for note in notes:
        lines.append(f"  note          : {note}")
    lines.append(status_line(None))
    return lines


def cmd_methods(args) -> int:
    from ..calib.fit import available_methods

    for name in available_methods():
        print(name)
    return EXIT_OK


def cmd_demo_path(args) -> int:
    from ..io.recording import bundled_recording_path

    print(bundled_recording_path())
    return EXIT_OK
