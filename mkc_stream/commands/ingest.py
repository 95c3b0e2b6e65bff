"""``record``, ``live`` and ``replay``: ingest from serial ports, CAN buses and logs.

    mkc-stream live --port /dev/ttyACM0 --protocol motioncal --out rec.csv
    mkc-stream live -i socketcan -c can0 --can-id 0x110 --duration 60 --json -
    mkc-stream record --port /dev/ttyUSB0 --baud 921600 --protocol binary --out rec.csv
    mkc-stream live --mavlink udpin:0.0.0.0:14550 --out rec.csv
    mkc-stream replay rec.csv --realtime
    mkc-stream replay log.mf4 --dbc imu.dbc --map mx=MagX,my=MagY,mz=MagZ

Heavy imports (numpy, numba, python-can, pyserial) happen inside the command functions.
"""
from __future__ import annotations

import argparse
import datetime
import math
import shutil
import sys

from .calreport import calibration_lines, status_line
from .common import (EXIT_OK, EXIT_REJECTED, EXIT_USAGE, Outputs, UsageError, add_json_option, add_quiet_option,
                     add_window_options, compiled_calibrator, fmt_vec, write_json)

EPILOG_SOURCE = ("SOURCE is --port PORT [--baud B] --protocol P for a serial port (PORT a device path or a "
                 "pyserial URL such as socket://host:port), or python-can's -i/--interface, -c/--channel, "
                 "-b/--bitrate [--bus-kwargs K=V ...] with --can-id ID or --dbc FILE --map COL=SIGNAL,... "
                 "for a CAN bus, or --mavlink CONN (a pymavlink connection string: udpin:0.0.0.0:14550, "
                 "tcp:host:port, a serial device) for an autopilot's MAVLink link.")

#: replay --realtime: the longest wall-clock wait between two samples (longer steps are shortened)
REPLAY_MAX_STEP_S = 1.0


# ----------------------------------------------------------------------------------------------
# parsers
# ----------------------------------------------------------------------------------------------


def _add_decoding(p):
    from .argtypes import can_id

    g = p.add_argument_group("CAN frame decoding")
    g.add_argument("--can-id", type=can_id,
                   help="arbitration id of the built-in frame layout (default 0x110; 11-bit or 29-bit)")
    g.add_argument("--dbc", metavar="FILE", help="decode frames through this DBC file (needs the [can-dbc] extra)")
    g.add_argument("--map", action="append", metavar="COL=[MSG.]SIGNAL[*SCALE],...",
                   help="with --dbc: which signals are mx, my, mz (required) and other columns")


def _add_source(p):
    from ..ingest.protocols import ALIASES, PROTOCOLS
    from .argtypes import positive_float, positive_int, writable_path

    g = p.add_argument_group("serial source")
    g.add_argument("--port", help="serial device path or pyserial URL (loop://, socket://host:port, ...)")
    g.add_argument("--baud", type=positive_int, default=115200, help="baud rate (default 115200)")
    g.add_argument("--protocol", choices=sorted(PROTOCOLS) + sorted(ALIASES), metavar="P",
                   help="serial protocol: " + "; ".join(f"{k}: {v}" for k, v in PROTOCOLS.items()))
    g.add_argument("--columns", help="--protocol csv: the header, when the device printed it before the port opened")
    g.add_argument("--reconnect", action="store_true", help="reopen a port that disappears instead of ending the run")
    # python-can's own flag names (can.cli.add_bus_arguments), declared here because importing
    # python-can costs more than half a second for every mkc-stream command
    b = p.add_argument_group("CAN source (python-can's flags)")
    b.add_argument("-i", "--interface", default=argparse.SUPPRESS,
                   help="python-can interface: socketcan, slcan, virtual, pcan, kvaser, vector, ...")
    b.add_argument("-c", "--channel", default=argparse.SUPPRESS,
                   help="python-can channel: can0, vcan0, /dev/ttyACM0 (slcan), a virtual channel name, ...")
    b.add_argument("-b", "--bitrate", type=positive_int, default=argparse.SUPPRESS, help="CAN bitrate, e.g. 500000")
    b.add_argument("--fd", action="store_true", default=argparse.SUPPRESS, help="CAN FD")
    b.add_argument("--data-bitrate", type=positive_int, default=argparse.SUPPRESS, help="CAN FD data-phase bitrate")
    b.add_argument("--bus-kwargs", nargs="+", default=argparse.SUPPRESS, metavar="KEY=VALUE",
                   help="more keyword arguments for can.Bus, e.g. sleep_after_open=0 tty_baudrate=921600")
    m = p.add_argument_group("MAVLink source (needs the [mavlink] extra)")
    m.add_argument("--mavlink", metavar="CONN",
                   help="pymavlink connection string: udpin:0.0.0.0:14550, udp:, udpout:HOST:PORT, tcp:HOST:PORT, "
                        "or a serial device (with --baud)")
    m.add_argument("--mavlink-message", metavar="MSG",
                   help="magnetometer message: RAW_IMU, SCALED_IMU, SCALED_IMU2, SCALED_IMU3, HIGHRES_IMU "
                        "(default: the first that arrives)")
    m.add_argument("--mavlink-rate", type=positive_float, default=100.0, metavar="HZ",
                   help="message rate to request from the autopilot (default 100 Hz)")
    m.add_argument("--link-timeout", type=positive_float, default=5.0, metavar="S",
                   help="end the run when the link sends nothing for S seconds (default 5)")
    _add_decoding(p)
    p.add_argument("--raw-out", metavar="FILE", type=writable_path,
                   help="CAN: also write every raw frame with python-can's writer for this suffix "
                        "(.log, .asc, .blf, .trc); record defaults to the --out name with .log")


def _add_run(p, what="live"):
    from .argtypes import positive_float, positive_int

    g = p.add_mutually_exclusive_group()
    g.add_argument("--max-samples", type=positive_int, metavar="N", help="stop after N samples")
    g.add_argument("--duration", type=positive_float, metavar="S",
                   help="stop after S seconds (" + ("sample time" if what == "replay" else "wall clock") + ")")
    p.add_argument("--progress", action="store_true", help="show the status line even when stderr is not a terminal")
    add_json_option(p)
    add_quiet_option(p)


def _add_out(p, help, required=False):
    from .argtypes import writable_path

    p.add_argument("--out", metavar="FILE", type=writable_path, required=required,
                   help=help + "; an existing file is refused unless --force (the input file always is)")
    p.add_argument("--force", action="store_true", help="overwrite an existing --out (and --raw-out) file")


def _add_calib(p):
    add_window_options(p, "samples kept in the calibration window (default 512, at most 65536)")


def register(subparsers):
    from .argtypes import float_range, input_file

    lv = subparsers.add_parser("live", help="calibrate live from a serial or CAN IMU",
                               description="Calibrate live from a serial or CAN IMU; ends with the accepted "
                                           "calibration. " + EPILOG_SOURCE)
    _add_source(lv)
    _add_run(lv)
    _add_out(lv, "also record what came in (recording CSV, .csv or .csv.gz)")
    _add_calib(lv)
    lv.set_defaults(func=cmd_live)

    rc = subparsers.add_parser("record", help="record a serial or CAN IMU to a recording CSV",
                               description="Record a serial or CAN IMU to a recording CSV (flushed every "
                                           "second). " + EPILOG_SOURCE)
    _add_source(rc)
    _add_run(rc, "record")
    _add_out(rc, "the recording CSV (.csv or .csv.gz)", required=True)
    rc.set_defaults(func=cmd_record)

    rp = subparsers.add_parser("replay", help="replay a recording or CAN log through the live calibrator",
                               description="Replay a recording (.csv, .csv.gz) or a python-can log (.log, .asc, "
                                           ".blf, .trc, .mf4) through the live calibrator, as fast as possible "
                                           "or in real time.")
    rp.add_argument("file", type=input_file, help="recording CSV or python-can log")
    rp.add_argument("--realtime", action="store_true",
                    help=f"at the pace of the timestamps; a time step longer than {REPLAY_MAX_STEP_S:g} s is "
                         "shortened to that and reported (a log's pause of hours does not hang the replay)")
    rp.add_argument("--speed", type=float_range(0.0, lo_open=True, allow_inf=True),
                    help="pace at this many times real time (implies --realtime)")
    _add_decoding(rp)
    _add_run(rp, "replay")
    _add_out(rp, "also write what was replayed as a recording CSV")
    _add_calib(rp)
    rp.set_defaults(func=cmd_replay)


# ----------------------------------------------------------------------------------------------
# opening sources
# ----------------------------------------------------------------------------------------------


def _open_live_source(args, notify, raw_out=None):
    from ..ingest.opener import can_decoder
    from ..ingest.source import SourceError

    is_can = any(hasattr(args, k) for k in ("interface", "channel"))
    if sum(map(bool, (args.port, is_can, args.mavlink))) > 1:
        raise UsageError("give one source: --port (serial), -i/-c (CAN) or --mavlink, not both")
    if not args.port and not is_can and not args.mavlink:
        raise UsageError("no source: give --port PORT --protocol P, -i INTERFACE -c CHANNEL, or --mavlink CONN")
    try:
        if args.mavlink:
            return _open_mavlink(args)
        if args.port:
            if not args.protocol:
                raise UsageError("--port needs --protocol (" + ", ".join(_protocols()) + ")")
            if args.dbc or args.map or args.can_id is not None:
                raise UsageError("--can-id/--dbc/--map apply to CAN sources, not to --port")
            from ..ingest.serial_source import SerialSource

            columns = [c.strip() for c in args.columns.split(",")] if args.columns else None
            return SerialSource(args.port, args.protocol, baud=args.baud, reconnect=args.reconnect,
                                columns=columns, notify=notify)
        from ..ingest.can_source import CanBusSource

        decoder = can_decoder(args.can_id, args.dbc, args.map, host_time=True)
        bus = _create_bus(args)
        url = f"can://{getattr(args, 'interface', '')}/{getattr(args, 'channel', '')}"
        return CanBusSource(bus, decoder, url=url, raw_out=raw_out)
    except SourceError as exc:
        raise UsageError(str(exc)) from None


def _open_mavlink(args):
    from ..ingest.mavlink_source import MAVLinkSource

    if args.protocol or args.dbc or args.map or args.can_id is not None:
        raise UsageError("--protocol/--can-id/--dbc/--map do not apply to --mavlink")
    return MAVLinkSource(args.mavlink, message=args.mavlink_message, rate_hz=args.mavlink_rate, baud=args.baud,
                         silence_s=args.link_timeout)


def _protocols():
    from ..ingest.protocols import PROTOCOLS

    return list(PROTOCOLS)


def _create_bus(args):
    """``can.Bus`` from python-can's flags (``--bus-kwargs`` values typed as python-can does)."""
    from ..ingest.can_source import open_bus
    from ..ingest.source import SourceError

    kwargs = {}
    for key in ("fd", "data_bitrate"):
        if hasattr(args, key):
            kwargs[key] = getattr(args, key)
    if hasattr(args, "bus_kwargs"):
        from can.util import cast_from_string

        for item in args.bus_kwargs:
            k, eq, v = item.partition("=")
            if not eq or not k:
                raise UsageError(f"--bus-kwargs entry {item!r} is not KEY=VALUE")
            kwargs[k.strip()] = cast_from_string(v.strip())
    try:
        return open_bus(getattr(args, "interface", None), getattr(args, "channel", None),
                        getattr(args, "bitrate", None), **kwargs)
    except SourceError as exc:
        raise UsageError(str(exc)) from None


def _default_raw_out(out):
    name = str(out)
    for suf in (".csv.gz", ".csv"):
        if name.lower().endswith(suf):
            return name[: -len(suf)] + ".log"
    return name + ".can.log"


# ----------------------------------------------------------------------------------------------
# the runs
# ----------------------------------------------------------------------------------------------


def _calibrator(args, unit):
    """A MagCalibrator whose kernels are compiled now, before any port is opened."""
    return compiled_calibrator(args.window, args.estep_every, unit, keep_history=False)


def _check_outputs(args, inputs=(), raw_out=None):
    """Before any work: --out/--raw-out are not an input and replace no file without --force."""
    from .argtypes import check_new_output

    check_new_output(args.out, args.force, inputs=inputs)
    check_new_output(raw_out, args.force, inputs=inputs, flag="--raw-out")


def _status_printer(args, label):
    show = args.progress or sys.stderr.isatty()
    if not show or args.quiet:
        return None, lambda: None
    width = max(40, shutil.get_terminal_size((120, 20)).columns - 1)

    def status(run):
        c = run.counts()
        cal = run.calibrator
        parts = [f"{label} {c['samples']:8d} samples", f"{run.rate:7.1f} Hz",
                 f"bad {c['bad_frames']}", f"drops {c['drops']}", f"gaps {c['gaps']}"]
        if cal is not None:
            cov = run.coverage
            parts.append("coverage " + ("-" if cov is None else f"{cov:.0%}"))
            acc = cal.accepted
            if acc is not None:
                parts.append(f"b {fmt_vec(acc.hard_iron, '').strip()} F {acc.field:.4g}")
                parts.append("ACCEPTED")
            else:
                parts.append(cal.status_reason())
        line = "  ".join(parts)
        sys.stderr.write("\r" + line[:width].ljust(width))
        sys.stderr.flush()

    def done():
        sys.stderr.write("\n")
        sys.stderr.flush()

    return status, done


def _notify(msg):
    print(f"\nmkc-stream: {msg}", file=sys.stderr, flush=True)


def _recorder(path, source, command):
    from ..ingest.recorder import RecordingWriter

    meta = dict(source.meta)
    meta["recorded_by"] = f"mkc-stream {command}"
    meta["started"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    return RecordingWriter(path, meta)


def _execute(args, source, cal, command, out_path):
    """Run the loop over ``source`` (closing it), with a recorder when ``out_path`` is given.
    Any exit from here (Ctrl-C, a lost port) still closes the source and the recorder."""
    from ..ingest.live import Run

    recorder = _recorder(out_path, source, command) if out_path else None
    status, done = _status_printer(args, command)
    run = Run(source, cal, recorder, max_samples=args.max_samples, duration=args.duration,
              duration_in_sample_time=(command == "replay"), status=status)
    try:
        result = run.run()
    finally:
        source.close()
        if status is not None:
            done()
    return run, result, recorder


def cmd_live(args) -> int:
    from ..ingest.threaded import QueuedReader

    _check_outputs(args, raw_out=args.raw_out)
    # units are known before the port opens for every built-in decoder (DBC: from the signal)
    cal = _calibrator(args, "uT")
    src = QueuedReader(_open_live_source(args, _notify, raw_out=args.raw_out))
    cal.unit = src.meta.get("units.mag", "uT")
    run, result, recorder = _execute(args, src, cal, "live", args.out)
    return _finish(args, "live", src, run, result, recorder)


def cmd_record(args) -> int:
    from ..ingest.threaded import QueuedReader

    is_can = any(hasattr(args, k) for k in ("interface", "channel"))
    raw_out = args.raw_out or (_default_raw_out(args.out) if is_can else None)
    _check_outputs(args, raw_out=raw_out)
    src = QueuedReader(_open_live_source(args, _notify, raw_out=raw_out))
    run, result, recorder = _execute(args, src, None, "record", args.out)
    return _finish(args, "record", src, run, result, recorder)


def cmd_replay(args) -> int:
    from ..ingest.opener import open_log
    from ..ingest.pacing import Paced
    from ..ingest.source import SourceError

    _check_outputs(args, inputs=[args.file])
    cal = _calibrator(args, "uT")
    try:
        src = open_log(args.file, can_id=args.can_id, dbc=args.dbc, mapping=args.map)
    except SourceError as exc:
        raise UsageError(str(exc)) from None
    cal.unit = src.meta.get("units.mag", "uT")
    if args.realtime or args.speed:
        src = Paced(src, speed=args.speed or 1.0, max_step_s=REPLAY_MAX_STEP_S)
    run, result, recorder = _execute(args, src, cal, "replay", args.out)
    return _finish(args, "replay", src, run, result, recorder)


# ----------------------------------------------------------------------------------------------
# the result
# ----------------------------------------------------------------------------------------------


def _result_json(command, src, run, result, recorder):
    counts = run.counts()
    cal = run.calibrator
    acc = None if cal is None else cal.accepted
    if acc is not None:
        obj = acc.to_json(counts=counts)
    else:
        from ..calib.result import Rejection, no_calibration_json

        why = Rejection("no_calibration", "no calibration (record)") if cal is None else cal.status()
        obj = no_calibration_json(why, counts)
    span = None if result.t_first is None else result.t_last - result.t_first
    obj.update({
        "command": command,
        "source": src.url,
        "protocol": src.meta.get("protocol") or src.meta.get("dbc_message") or src.meta.get("can_id"),
        "time_source": src.meta.get("time_source"),
        "units": {"mag": src.meta.get("units.mag", "uT")},
        "ended": result.ended,
        "message": result.message,
        "elapsed_s": result.elapsed_s,
        "cpu_percent": result.cpu_percent,
        "samples_per_second": result.samples / result.elapsed_s if result.elapsed_s > 0 else None,
        "sample_rate_hz": (result.samples - 1) / span if span and span > 0 and math.isfinite(span) else None,
        "ingest": src.detail(),
        "recording": None if recorder is None else str(recorder.path),
        "recorded_rows": None if recorder is None else recorder.rows,
        "raw_frames": src.meta.get("raw_frames"),
        "unfed_at_stop": result.unfed,
    })
    if recorder is not None and recorder.unrecorded:
        obj["unrecorded_fields"] = dict(recorder.unrecorded)
    if cal is not None:
        obj.update({"method": "mkc-em-stream", "window": cal.stream.config.window,
                    "estep_every": cal.stream.config.estep_every, "first_accepted_at_sample": cal.first_accepted_at})
    ids = getattr(src.decoder, "ids_seen", None)
    if ids is not None:
        obj["can_ids_seen"] = {hex(k): v for k, v in ids.most_common(10)}
    return obj


def _report(command, src, run, result, recorder, obj, out):
    p = lambda s="": print(s, file=out)  # noqa: E731
    c = obj["counts"]
    d = obj["ingest"]
    unit = obj["units"]["mag"]
    proto = obj.get("protocol")
    p(f"mkc-stream {command}: {src.url}" + (f" ({proto})" if proto else ""))
    rate = obj["sample_rate_hz"]
    p(f"  read          : {c['samples']} samples in {result.elapsed_s:.1f} s"
      + (f" ({rate:.1f} Hz by {obj['time_source']} time)" if rate else "")
      + f", {c['bad_frames']} bad frames, {c['drops']} drops, {c['gaps']} gaps")
    extra = [f"{d[k]} {k.replace('_', ' ')}" for k in ("resyncs", "skipped_bytes", "lead_in_bytes", "ignored",
                                                       "truncated", "seq_resets", "reconnects") if d.get(k)]
    if extra:
        p(f"  ingest        : {', '.join(extra)}")
    for why in d.get("bad_reasons", [])[:3]:
        p(f"  bad frame     : {why}")
    if obj.get("can_ids_seen") and not c["samples"]:
        ids = ", ".join(f"{k} x{v}" for k, v in obj["can_ids_seen"].items())
        p(f"  no sample     : no frame matched; ids in the data: {ids} (use --can-id, or --dbc with --map)")
    ended = result.ended + (f": {result.message}" if result.message else "")
    p(f"  ended         : {ended}")
    if d.get("stopped_early"):
        p(f"  warning       : {d['stopped_early']}")
    if d.get("queue_dropped"):
        p(f"  overload      : {d['queue_dropped']} samples dropped in {d['queue_drop_events']} batches: the "
          f"calibrator fell behind the source (queue of {d['queue_capacity']} samples full; counted in drops)")
    if result.ended == "interrupted" and (d.get("unprocessed_at_close") or result.unfed):
        p(f"  at the stop   : {d.get('unprocessed_at_close', 0)} samples still queued (not read), {result.unfed} read "
          "and recorded but not calibrated")
    if d.get("paced_long_steps"):
        p(f"  paced         : {d['paced_long_steps']} time steps longer than {REPLAY_MAX_STEP_S:g} s were shortened "
          f"to {REPLAY_MAX_STEP_S:g} s ({d['paced_skipped_s']:.4g} s of waiting skipped)")
    if recorder is not None:
        p(f"  recording     : {recorder.path} ({recorder.rows} rows" +
          (", intact up to the last sample read)" if result.ended == "source lost" else ")"))
    if obj.get("raw_frames"):
        p(f"  raw frames    : {obj['raw_frames']} ({d.get('raw_frames', 0)} frames)")
    if obj.get("unrecorded_fields"):
        p(f"  not recorded  : {obj['unrecorded_fields']} (fields that appeared after the header was written)")
    if result.cpu_percent is not None:
        p(f"  cpu           : {result.cpu_percent:.1f}% of one core ({obj['samples_per_second']:,.0f} samples/s)")
    cal = run.calibrator
    if cal is None:
        return
    acc = cal.accepted
    if acc is None:
        p(status_line(cal.status()))
        return
    for line in calibration_lines(acc, unit, first_accepted_at=cal.first_accepted_at):
        p(line)


def _finish(args, command, src, run, result, recorder) -> int:
    obj = _result_json(command, src, run, result, recorder)
    if not args.quiet:
        _report(command, src, run, result, recorder, obj, sys.stderr if args.json == "-" else sys.stdout)
    if result.ended == "source lost":
        print(f"mkc-stream: {result.message}; the run ended"
              + (f", {recorder.rows} samples are in {recorder.path}" if recorder is not None else ""),
              file=sys.stderr)
    outputs = Outputs()
    if args.json:              # write_json prints the result to stdout if its file cannot be written
        outputs.attempt(args.json, write_json, obj, args.json)
    if result.ended == "source lost":
        return outputs.done(EXIT_USAGE)
    if command == "record":
        return outputs.done(EXIT_OK)
    return outputs.done(EXIT_OK if obj["status"] == "accepted" else EXIT_REJECTED)

