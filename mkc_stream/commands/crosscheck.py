"""`mkc-stream crosscheck RECORDING`: the Python streaming calibrator beside the C99 port (firmware_ref/).

Both run MagCalibrator's algorithm over the same recording; at every E-step checkpoint the state
(theta, sigma, d, a, the feature normalisation) and the trial calibration (b, S, F, quality) are
compared, and the largest relative difference per quantity is reported. Exit 0 when every quantity
is within its tolerance (mkc_stream.cport.compare.TOLERANCES) and the decisions agree, 1 on a mismatch,
2 when the recording cannot be read, the C port cannot be built here, or nothing could be compared
(no checkpoint at all, e.g. fewer samples than a window; for float, no well-posed checkpoint for the
teacher-forced criterion, e.g. collinear or planar data): a comparison that was not made is not "OK".

--precision double (default): the C double build runs free beside the reference; equal to <= 1e-9.
--precision float: the float build, free-running (reported) and teacher-forced (the pass criterion:
  started from the reference's state at each checkpoint, its next checkpoint within 1e-4 on theta
  and the calibration, on every well-posed checkpoint).
"""
from __future__ import annotations

import sys

from .common import (EXIT_OK, EXIT_REJECTED, EXIT_USAGE, Outputs, UsageError, add_json_option, add_quiet_option,
                     add_window_options, load_recording, write_json)


def register(subparsers):
    from .argtypes import input_file

    p = subparsers.add_parser("crosscheck", help="compare the C99 port (firmware_ref/) with the Python calibrator",
                              description="Compare the C99 port with the Python calibrator on one recording. "
                                          "Exit 0 all within tolerance, 1 mismatch, 2 unreadable input, no C port, "
                                          "or nothing compared.")
    p.add_argument("recording", type=input_file, help="recording CSV (docs/spec/recording.md); 'demo' for the bundled one")
    add_window_options(p, "samples kept in the window (default 512, as calibrate --stream)")
    p.add_argument("--precision", choices=("double", "float", "both"), default="double",
                   help="which C build to compare (default double)")
    add_json_option(p, "the report as JSON")
    add_quiet_option(p)
    p.set_defaults(func=cmd_crosscheck)


def _fmt(x):
    return "-" if x is None else f"{x:.3g}"


def cmd_crosscheck(args) -> int:
    from .. import cport as FW

    rec = load_recording(args.recording)
    precisions = ("double", "float") if args.precision == "both" else (args.precision,)
    try:
        for prec in precisions:
            lib = FW.load(prec)
            if args.window > lib.W:
                raise UsageError(f"--window {args.window} is larger than the C build's capacity MKC_W = {lib.W}")
    except FW.FirmwareUnavailable as exc:
        raise UsageError(f"the C port is not available here: {exc}") from exc
    unit = rec.mag_unit
    mags = rec.mag
    W, K = args.window, args.estep_every
    need_state = "float" in precisions
    py, _ = FW.python_checkpoints(mags, W, K, unit, capture_state=need_state)
    report = {"recording": str(args.recording), "samples": int(len(mags)), "window": W, "estep_every": K,
              "reference_feedback": "portable (calib/portable.py)", "checkpoints_python": len(py), "results": {}}
    ok, not_compared = True, []
    out = sys.stderr if args.json == "-" else sys.stdout
    for prec in precisions:
        cc, _ = FW.c_checkpoints(mags, W, K, unit, precision=prec)
        free = FW.compare_checkpoints(py, cc)
        res = {"checkpoints_c": len(cc), "free_running": {"max_rel": free.max_rel, "at_sample": free.where,
                                                          "mismatches": free.mismatches}}
        if prec == "double":
            fails = free.failures("double")
            res["tolerances"] = FW.TOLERANCES["double"]
        else:
            seg = FW.segment_comparison(mags, py, W, K, unit, precision="float")
            res["teacher_forced"] = {"checkpoints": seg.checkpoints_python, "max_rel": seg.max_rel,
                                     "at_sample": seg.where, "mismatches": seg.mismatches}
            res["tolerances"] = {k: FW.TOLERANCES["float"][k] for k in FW.CORE_QUANTITIES}
            fails = seg.failures("float", FW.CORE_QUANTITIES)
            fails += [m for m in free.mismatches if "python at sample" in m or "count" in m]
        # what the verdict rests on must have been compared at least once
        if not py or not cc:
            unmade = (f"no checkpoint to compare (python {len(py)}, C {len(cc)}): the recording has "
                      f"{len(mags)} samples, the first checkpoint needs a filled window of up to {W}")
        elif prec == "float" and seg.checkpoints_python == 0:
            unmade = ("no well-posed checkpoint for the teacher-forced criterion (an ellipsoid fit covering half "
                      "the sphere): the data do not span the sphere, e.g. collinear or planar")
        else:
            unmade = None
        res["failures"] = fails
        res["compared"] = unmade is None
        res["not_compared_reason"] = unmade
        res["ok"] = not fails and unmade is None
        ok = ok and res["ok"]
        if unmade:
            not_compared.append((prec, unmade))
        report["results"][prec] = res
        if not args.quiet:
            print(f"mkc-stream crosscheck: {args.recording} ({len(mags)} samples, window {W}, E-step every {K}; "
                  f"C {prec} build, Python reference)", file=out)
            print(f"  checkpoints   : python {len(py)}, C {len(cc)}", file=out)
            keys = ["theta", "sigma", "d", "a", "c0s0", "hard_iron", "soft_iron", "field", "quality", "condition"]
            rows = [("free-running", free)] + ([("teacher-forced", seg)] if prec == "float" else [])
            for label, cmp in rows:
                print(f"  {label:14s}: " + ", ".join(f"{k} {_fmt(cmp.max_rel.get(k))}" for k in keys), file=out)
            if fails:
                status = "MISMATCH - " + "; ".join(fails[:4])
            elif unmade:
                status = "NOT COMPARED - " + unmade
            else:
                status = "OK"
            print(f"  status        : {status}", file=out)
    report["ok"] = ok
    outputs = Outputs()
    if args.json:
        outputs.attempt(args.json, write_json, report, args.json)
    if not ok and not_compared and all(not r["failures"] for r in report["results"].values()):
        outputs.done(EXIT_USAGE)
        prec, why = not_compared[0]
        what = "nothing was compared" if len(not_compared) == len(precisions) else f"the {prec} build was not compared"
        raise UsageError(f"{args.recording}: {what}: {why}")
    return outputs.done(EXIT_OK if ok else EXIT_REJECTED)

