"""`calibrate --attitude`: the attitude-aided flight calibration (mkc_stream/flight) on the command line.

Chosen by default when the recording has an attitude (qw, qx, qy, qz) and a position (lat, lon) or
--lat/--lon is given, since a flight rarely covers enough of the sphere for the ellipsoid fit; the
ellipsoid fit with --no-attitude. Its result is the `calibrate` object of
docs/spec/machine-output.md with `compensation` and `earth_field`. With --plot the report of each fit
(flight/report_plot.py) is drawn after the result is written; --all-instances draws one PNG per
compass, PATH's name with -instance<id> before its extension.
"""
from __future__ import annotations

import math

from .calreport import status_line
from .common import fmt_vec

QUAT = ("qw", "qx", "qy", "qz")
#: the fitted gain (sensor uT per model uT) must lie within this fraction of 1 for a log in uT
FIELD_TOLERANCE = 0.15


def add_attitude_options(p):
    g = p.add_argument_group("attitude-aided calibration (flight and robot logs)")
    g.add_argument("--attitude", dest="attitude", action="store_true", default=None,
                   help="fit the vector model against the Earth field with the log's attitude (default when the "
                        "recording has an attitude and a position or --lat/--lon)")
    g.add_argument("--no-attitude", dest="attitude", action="store_false", help="the ellipsoid fit, even for a flight")
    g.add_argument("--lat", type=float, help="latitude (deg) for the Earth-field model when the log has no GPS")
    g.add_argument("--lon", type=float, help="longitude (deg)")
    g.add_argument("--alt", type=float, default=0.0, help="altitude above the WGS84 ellipsoid (m), default 0")
    g.add_argument("--date", help="date for the Earth-field model (YYYY-MM-DD or a decimal year), default the log's")
    g.add_argument("--yaw-only", action="store_true",
                   help="ground robots: hard iron and horizontal soft iron from yaw alone, vertical terms held")
    g.add_argument("--tilt-sd-deg", type=_tilt_sd, default="auto", metavar="DEG|auto|off",
                   help="the attitude's roll/pitch error (deg, 1 sd) the fit corrects for; 'auto' (default) "
                        "estimates it from the fit's residuals, 'off' does not correct; the batch fit only (docs/flight.md)")
    g.add_argument("--all-instances", action="store_true",
                   help="calibrate every magnetometer of the log and compare them (heading, field vs the model); "
                        "names the inconsistent one")


def _tilt_sd(text):
    """--tilt-sd-deg: a non-negative angle in deg, 'auto' or 'off' (None)."""
    import argparse

    if text in ("auto", "off"):
        return None if text == "off" else text
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"expected an angle >= 0 in deg, 'auto' or 'off'; got {text!r}")
    return v


def wants_attitude(args, rec) -> bool:
    if args.attitude is not None:
        return args.attitude
    has_q = all(c in rec.aux for c in QUAT)
    has_pos = (args.lat is not None and args.lon is not None) or ("lat" in rec.aux and "lon" in rec.aux)
    return has_q and has_pos


def attitude_calibrate(args, rec, unit, counts, plots=None, plot_path=None, label=""):
    """(json object, the FlightCalibration when accepted else None, report lines) of the attitude-aided fit.
    plots: a list that receives (plot path, rec, FlightCalibration, label) for write_flight_plots when --plot is
    given and the fit ran (accepted or rejected, as the ellipsoid fit's plot); plot_path: instead of --plot's;
    label: added to the figure's title."""
    from .._validation import MKCInputError
    from ..calib.result import Rejection, no_calibration_json
    from ..flight import fit_flight

    if (args.lat is None) != (args.lon is None):
        from .common import UsageError

        raise UsageError("--lat and --lon go together")
    try:
        fc = fit_flight(rec, lat=args.lat, lon=args.lon, alt=args.alt, date=args.date, yaw_only=args.yaw_only,
                        tilt_sd_deg=getattr(args, "tilt_sd_deg", "auto"))
    except (MKCInputError, ValueError, ImportError) as exc:
        rejection = Rejection("not_observable" if isinstance(exc, MKCInputError) else "no_calibration", str(exc))
        return no_calibration_json(rejection, counts, method="mkc-em-attitude"), None, [status_line(rejection)]
    if plots is not None and getattr(args, "plot", None):
        plots.append((plot_path or args.plot, rec, fc, label))
    rejection = None
    from ..flight.calibrate import YAW_ERROR_LIMIT_DEG

    if fc.yaw_error_rms_deg is not None and fc.yaw_error_rms_deg > YAW_ERROR_LIMIT_DEG:
        rejection = Rejection("rejected", f"the attitude's fitted yaw error is {fc.yaw_error_rms_deg:.1f} deg RMS (more "
                                          f"than {YAW_ERROR_LIMIT_DEG:g}): the log's heading and the magnetometer "
                                          "disagree beyond a wandering yaw error (a heading offset of the attitude or "
                                          "a wrong declination?)", ("attitude_yaw",),
                              {"yaw_error_rms_deg": fc.yaw_error_rms_deg})
    elif unit == "uT" and math.isfinite(fc.scale) and abs(fc.scale - 1.0) > FIELD_TOLERANCE:
        rejection = Rejection("rejected", f"fitted field {fc.scale:.3f} x the Earth-field model (more than "
                                          f"{FIELD_TOLERANCE:.0%} from 1): wrong unit, position or date, or a "
                                          "disturbance that does not move with the vehicle",
                              ("field_model",), {"scale": fc.scale})
    obj = fc.to_json()
    obj.update({"quality": {"residual_rms": None, "coverage": None, "outlier_fraction": None, "condition": None},
                "status": "accepted" if rejection is None else "rejected",
                "reason": None if rejection is None else rejection.text, "counts": counts,
                "method": "mkc-em-attitude"})
    if rejection is not None:
        obj["rejection"] = rejection.to_json()
    return obj, (fc if rejection is None else None), report_lines(fc, unit, rejection)


def report_lines(fc, unit, rejection) -> list:
    S = fc.soft_iron
    lines = ["  method        : mkc-em-attitude (vector model against the Earth field, the log's attitude)",
             f"  hard iron b   : {fmt_vec(fc.hard_iron, unit)}",
             f"  soft iron S   : {fmt_vec(S[0], '')}", f"                  {fmt_vec(S[1], '')}",
             f"                  {fmt_vec(S[2], '')}   (m_cal = S (m_raw - b), det S = 1)",
             f"  field F       : {fc.field:.5g} {unit}"]
    if fc.earth is not None:
        e = fc.earth
        lines.append(f"  Earth field   : {e.model}: {e.intensity_uT:.2f} uT, inclination {e.inclination_deg:.2f} deg, "
                     f"declination {e.declination_deg:.2f} deg; fitted gain {fc.scale:.4f} {unit} per uT")
    if fc.current is not None:
        ci = "" if fc.current_ci is None else "  95%: " + ", ".join(f"[{a:.3g}, {b:.3g}]" for a, b in fc.current_ci)
        lines.append(f"  current       : {fmt_vec(fc.current, unit + '/A')}{ci}")
    if fc.throttle is not None:
        lines.append(f"  throttle      : {fmt_vec(fc.throttle, unit)} at full throttle")
    if fc.delay_s is not None:
        ci = "" if fc.delay_ci_s is None else f", 95% [{fc.delay_ci_s[0] * 1e3:+.0f}, {fc.delay_ci_s[1] * 1e3:+.0f}]"
        lines.append(f"  delay         : {fc.delay_s * 1e3:+.1f} ms{ci} (" + (
            "the magnetometer sees the power signal this late)" if fc.delay_s >= 0
            else "the logged power signal is this late: a filtered or late-logged sensor)"))
    lines.append(f"  misalignment  : {fmt_vec(fc.misalignment_deg, 'deg')} (rotation vector, sensor to attitude frame; "
                 "not in the calibration)")
    if fc.fit.tilt_sd_deg:
        how = "estimated from the residuals" if fc.fit.tilt_sd_estimated is not None else "as given"
        lines.append(f"  tilt error    : {fc.fit.tilt_sd_deg:.2f} deg RMS in the log's roll/pitch ({how}), corrected for")
    lines.append(f"  samples       : {fc.samples} used, {fc.skipped} without attitude or power left out")
    if fc.held:
        lines.append(f"  held          : {', '.join(fc.held)} (not observable in this log: kept at their prior)")
    for note in fc.notes:
        lines.append(f"  note          : {note}")
    lines.append(status_line(rejection))
    return lines


def all_instances(args, path, out, plots=None):
    """(json object, every compass accepted?, [(instance number, FlightCalibration)] of the accepted ones)
    of --all-instances: every compass of a flight log calibrated, then compared. plots: as attitude_calibrate's,
    one PNG per compass (report_plot.instance_path)."""
    from ..flight.report_plot import instance_path
    from ..flight.compare import compare_compasses
    from ..ingest.flightlogs import inspect_flight_log, is_flight_log, read_flight_log
    from .common import UsageError

    if not is_flight_log(path):
        raise UsageError(f"--all-instances needs a flight log or bag with several magnetometers; {path} is not one")
    try:
        ids = [str(i["id"]) for i in inspect_flight_log(path)["instances"]]
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot read {path}: {exc}") from None
    results, accepted, intensity = [], [], None
    for cid in ids:
        rec = read_flight_log(f"{path}#instance={cid}")
        unit = rec.mag_unit
        plot_path = instance_path(args.plot, cid) if getattr(args, "plot", None) else None
        obj, fc, lines = attitude_calibrate(args, rec, unit, rec.counts(), plots, plot_path, f"instance {cid}")
        if plots and plots[-1][0] == plot_path:
            lines.insert(-1, f"  plot          : {plot_path}")
        obj["instance"] = cid
        results.append(obj)
        if out is not None:
            print(f"mkc-stream calibrate --all-instances: {path} instance {cid}", file=out)
            for line in lines:
                print(line, file=out)
        if fc is not None:
            accepted.append((cid, rec, fc))
            if fc.earth is not None:
                intensity = fc.earth.intensity_uT
    comparison = compare_compasses(accepted, intensity)
    if out is not None:
        print(f"compasses compared: {len(accepted)} of {len(ids)} calibrated", file=out)
        for row in comparison["compasses"]:
            vs = f" ({row['field_vs_model']:+.1%} vs the model)" if "field_vs_model" in row else ""
            heads = ", ".join(f"{d:.2f} deg RMS from {j}" for j, d in row["heading_rms_deg"].items())
            print(f"  instance {row['id']}: field {row['field_uT']:.2f} uT{vs}; heading {heads}", file=out)
        if comparison.get("note"):
            print(f"  note          : {comparison['note']}", file=out)
        for bad in comparison["inconsistent"]:
            print(f"  INCONSISTENT  : instance {bad['id']}: {bad['reason']}", file=out)
    numbered = [(k, fc) for k, cid in enumerate(ids) for c, _, fc in accepted if c == cid]
    return {"instances": results, "comparison": comparison, "recording": str(path)}, len(accepted) == len(ids), numbered


def write_flight_plots(outputs, plots, title):
    """Draw each (path, rec, FlightCalibration, label) of plots (flight/report_plot.py) titled with the recording
    and the label; a failed write goes to outputs (exit 2 at the end) and does not stop the others."""
    import os

    from ..flight.report_plot import plot_flight_report

    for path, rec, fc, label in plots:
        try:
            outputs.attempt(path, plot_flight_report, rec, fc, path, title=f"{os.path.basename(str(title))} {label}".strip())
        except ValueError as exc:             # a recording the calibration does not fit (not expected here)
            outputs.failed.append(f"no plot written to {path}: {exc}")
