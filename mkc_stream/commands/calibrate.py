"""`calibrate` (a recording, batch or --stream), `methods` (the calibration methods) and `demo-path`."""
from __future__ import annotations

import math
import sys
import time

from .common import (EXIT_OK, EXIT_REJECTED, Outputs, Progress, add_json_option, add_quiet_option, add_window_options,
                     check_plot_extra, compiled_calibrator, fmt_vec, load_recording, write_json)


def register(subparsers):
    from .argtypes import input_file, writable_path

    c = subparsers.add_parser("calibrate", help="calibrate a magnetometer recording (batch)")
    c.add_argument("recording", type=input_file,
                   help="recording CSV (docs/spec/recording.md), .csv or .csv.gz; 'demo' for the bundled one")
    c.add_argument("--method", default="mkc-em-geo-dir",
                   help="mkc-em-geo-dir (default: the geometric MKC-EM with direction weighting), mkc-em-geo, "
                        "mkc-em (the paper's algebraic form), mkc, ls, or a baseline (see `mkc-stream methods`)")
    add_json_option(c)
    c.add_argument("--plot", metavar="PNG", type=writable_path, help="save a plot of the fit (needs the [plot] extra)")
    add_quiet_option(c, "no human report and no progress")
    c.add_argument("--stream", action="store_true", help="replay through the streaming calibrator (MKC-EM on a window)")
    add_window_options(c, when="--stream: ")
    c.set_defaults(func=cmd_calibrate)

    m = subparsers.add_parser("methods", help="list the calibration methods")
    m.set_defaults(func=cmd_methods)

    d = subparsers.add_parser("demo-path", help="print the path of the bundled real recording")
    d.set_defaults(func=cmd_demo_path)


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
    p(f"  hard iron b   : {fmt_vec(fit.hard_iron, unit)}")
    S = fit.soft_iron
    p(f"  soft iron S   : {fmt_vec(S[0], '')}")
    p(f"                  {fmt_vec(S[1], '')}")
    p(f"                  {fmt_vec(S[2], '')}   (m_cal = S (m_raw - b), det S = 1)")
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
    _report_uncertainty(p, fit.uncertainty, unit)
    p(f"  status        : {'ACCEPTED' if accepted else 'REJECTED - ' + reason}")


def _report_uncertainty(p, u, unit):
    if u and all(math.isfinite(v) for v in u["hard_iron_sd"]):
        p(f"  uncertainty   : hard iron sd {fmt_vec(u['hard_iron_sd'], unit)}, heading sd "
          f"{u['heading_sd_deg']:.2f} deg (level, horizontal field = F; lower bounds: samples taken as independent)")


def cmd_calibrate(args) -> int:
    from ..calib.acceptance import check
    from ..calib.confidence import calibration_uncertainty
    from ..calib.ellipsoid import EllipsoidError
    from ..calib.fit import fit_ellipsoid, make_estimator

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
        fit.uncertainty = calibration_uncertainty(rec.mag, fit.hard_iron, fit.soft_iron, fit.field)
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
        from ..plots import plot_calibration

        outputs.attempt(args.plot, plot_calibration, rec.mag, fit, args.plot, title=str(args.recording))
    return outputs.done(EXIT_OK if accepted else EXIT_REJECTED)


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
            p(f"  hard iron b   : {fmt_vec(acc.hard_iron, unit)}")
            for i, row in enumerate(acc.soft_iron):
                p(("  soft iron S   : " if i == 0 else "                  ") + fmt_vec(row, ""))
            p(f"  field F       : {acc.field:.5g} {unit}")
            p(f"  kernel        : sigma {acc.sigma:.4g}, d {acc.d:.4g}")
            q = acc.quality
            p(f"  quality       : inlier residual rms {q['residual_rms']:.4g} {unit}, coverage {q['coverage']:.0%}, "
              f"outliers {q['outlier_fraction']:.1%}, condition {q['condition']:.3g}")
            _report_uncertainty(p, acc.uncertainty, unit)
            p("  status        : ACCEPTED")
    return obj, acc is not None


def cmd_methods(args) -> int:
    from ..calib.fit import available_methods

    for name in available_methods():
        print(name)
    return EXIT_OK


def cmd_demo_path(args) -> int:
    from ..io.recording import bundled_recording_path

    print(bundled_recording_path())
    return EXIT_OK
