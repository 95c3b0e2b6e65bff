"""``inspect``: what a flight log, bag or recording holds, before reading it as a recording.

    mkc-stream inspect flight.bin
    mkc-stream inspect flight.ulg --json -

Per magnetometer instance: its ``id`` (what ``LOG#instance=ID`` takes), samples, mean rate
((n - 1) / duration, Hz), duration (s), aux columns and the autopilot's applied calibration; the
JSON object is the ``inspect`` one of docs/spec/machine-output.md.
"""
from __future__ import annotations

import json
import pathlib
import sys

from .common import EXIT_OK, Outputs, UsageError, add_json_option, add_quiet_option, write_json


def register(subparsers):
    p = subparsers.add_parser("inspect", help="list what a flight log, bag or recording holds",
                              description="List the magnetometer instances of a flight log (PX4 ULog, ArduPilot "
                                          "DataFlash, .px4log, MAVLink .tlog), a ROS bag or a recording CSV: id, "
                                          "samples, rate, duration, aux columns, applied calibration.")
    p.add_argument("recording", metavar="LOG", help="flight log, ROS bag (ROS 2: its folder) or recording CSV")
    add_json_option(p, "the listing")
    add_quiet_option(p)
    p.set_defaults(func=cmd_inspect)


def _format_key(path, fmt: str) -> str:
    """The spec's short format name (a ROS 2 bag given as its .mcap file: ``mcap``)."""
    return "mcap" if fmt == "rosbag2" and pathlib.Path(path).suffix.lower() == ".mcap" else fmt


def inspect_log(path) -> dict:
    """The listing of ``path`` (a flight log, bag or recording); UsageError when it is none of them."""
    from ..ingest.flightlogs import inspect_flight_log, sniff_format
    from ..ingest.logs import is_can_log

    path = str(path)
    fmt = sniff_format(path)
    try:
        if fmt is not None:
            got = inspect_flight_log(path)
            out = {"format": _format_key(path, fmt), "format_name": got["format"], "path": path}
            out["instances"] = [dict(inst, id=str(inst["id"])) for inst in got["instances"]]
            out["damage"] = got.get("damage", [])
            return out
        p = pathlib.Path(path)
        if p.is_dir():
            raise UsageError(f"cannot read {path}: a directory that is not a ROS 2 bag (no metadata.yaml)")
        if p.is_file() and is_can_log(p):
            raise UsageError(f"cannot read {path}: a CAN log holds frames, not a recording; replay it "
                             "(mkc-stream replay LOG --can-id ID) to see its samples")
        return _inspect_recording(path)
    except (OSError, ValueError) as exc:        # RecordingError and FlightLogError are ValueErrors
        raise UsageError(f"cannot read {path}: {exc}") from None
    except MemoryError:
        raise UsageError(f"cannot read {path}: it does not fit in memory") from None


def _inspect_recording(path) -> dict:
    from ..ingest.flightlogs._common import rate_of
    from ..io.recording import read_recording

    rec = read_recording(path)
    applied = rec.meta.get("applied_calibration")
    if applied is not None:
        try:
            applied = json.loads(applied)
        except ValueError:
            applied = {"text": applied}
    t = rec.t
    inst = {"id": "0", "samples": int(len(t)), "rate_hz": rate_of(t),
            "duration_s": float(t[-1] - t[0]) if len(t) else 0.0, "aux": sorted(rec.aux),
            "applied_calibration": applied, "units": rec.mag_unit}
    if "calibration" in rec.meta:
        inst["calibration"] = rec.meta["calibration"]
    damage = [f"line {line}: {why}" for line, why in rec.bad_rows[:20]]
    return {"format": "recording", "format_name": "recording CSV", "path": str(path), "instances": [inst],
            "damage": damage, "damage_count": len(rec.bad_rows)}


def _fmt(v, spec, unit=""):
    return "-" if v is None else f"{v:{spec}}{unit}"


def _report(obj, out):
    p = lambda s="": print(s, file=out)  # noqa: E731
    p(f"{obj['path']}: {obj['format_name']} ({obj['format']}), {len(obj['instances'])} magnetometer instance(s)")
    for inst in obj["instances"]:
        name = f" {inst['topic']}" if inst.get("topic") else ""
        p(f"  id {inst['id']}{name}: {inst['samples']} samples, {_fmt(inst['rate_hz'], '.4g', ' Hz')}, "
          f"{_fmt(inst['duration_s'], '.4g', ' s')}")
        p(f"      aux: {', '.join(inst['aux']) or 'none'}")
        if inst.get("calibration"):
            p(f"      calibration: {inst['calibration']}")
        if inst.get("applied_calibration"):
            p(f"      applied calibration: {json.dumps(inst['applied_calibration'])[:200]}")
    for why in obj.get("damage", [])[:5]:
        p(f"  damage: {why}")
    if len(obj.get("damage", [])) > 5:
        p(f"  damage: {len(obj['damage']) - 5} more")


def cmd_inspect(args) -> int:
    obj = inspect_log(args.recording)
    if not args.quiet:
        _report(obj, sys.stderr if args.json == "-" else sys.stdout)
    outputs = Outputs()
    if args.json:
        outputs.attempt(args.json, write_json, obj, args.json)
    return outputs.done(EXIT_OK)
