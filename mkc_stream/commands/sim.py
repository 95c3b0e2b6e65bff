"""`simulate` (a recording from the sensor simulator) and `diagnose` (the sim-to-real gap)."""
from __future__ import annotations

import sys

from .common import (EXIT_OK, EXIT_REJECTED, Outputs, UsageError, add_json_option, add_quiet_option, load_recording,
                     write_json)

#: the generated trajectory kinds (mkc_stream.sim.trajectory.MOTIONS, spelled out here so the CLI
#: starts without importing the simulator)
TRAJECTORIES = ("hand", "figure8", "flight", "ground", "static")


#: simulate refuses more samples than this (duration x rate): simulating takes ~2 KB of memory
#: and ~80 us per sample (10^6 samples: 2 GB, 80 s), and a typo of a few zeros should not do that.
MAX_SIM_SAMPLES = 2_000_000

#: hard limits of effect parameters, beyond the finite check every parameter gets: outside them an
#: effect's output is no longer a recording (sample_drops fraction 1.5 left one sample; saturation
#: at 0 uT makes every sample zero). The library's Param ranges are realistic ranges, not limits.
EFFECT_LIMITS = {
    ("sample_drops", "fraction"): (0.0, 1.0, "a fraction of the samples, 0 <= f < 1", True),
    ("sample_drops", "run"): (1.0, None, "a mean run length, >= 1 sample", False),
    ("saturation", "limit"): (0.0, None, "an output range, > 0", True),
    ("higher_order_soft_iron", "pattern"): (0.0, None, "a pattern seed, >= 0", False),
}
#: parameter names that are scales, rates or time constants (>= 0) in every effect that has them
NONNEGATIVE_PARAMS = {"tau", "sigma", "spread", "width", "q", "kurtosis", "lsb", "rate"}


def register(subparsers):
    from .argtypes import (float_range, fraction, input_file, int_range, nonneg_float, nonneg_int, positive_float,
                           vector3, writable_dir, writable_path)

    s = subparsers.add_parser("simulate", help="simulate a magnetometer/IMU recording with effects")
    s.add_argument("--trajectory", default="hand",
                   help="hand (tumbling, the whole sphere), figure8, flight (banked turns), ground (a vehicle "
                        "turning about the vertical), static (at rest in one attitude), or recording:PATH to "
                        "replay a recording's times, directions and aux")
    s.add_argument("--duration", type=positive_float, default=200.0, help="seconds (generated trajectories)")
    s.add_argument("--rate", type=positive_float, default=50.0, help="samples per second (generated trajectories)")
    s.add_argument("--temp", default="cycle", choices=("cycle", "ramp", "const", "none"), help="temperature profile")
    s.add_argument("--power", action="store_true", help="add flight-like throttle, current and voltage columns")
    s.add_argument("--no-other-loads", action="store_true", help="current follows throttle only")
    s.add_argument("--field", type=positive_float, default=50.0, help="field strength, uT")
    s.add_argument("--noise", type=nonneg_float, default=0.1, help="white noise per axis, uT RMS")
    s.add_argument("--hard-iron", type=vector3, default=(12.0, -7.0, 20.0), help="b as x,y,z in uT (default 12,-7,20)")
    s.add_argument("--lsb", type=nonneg_float, default=0.0, help="output resolution, uT (0 = continuous)")
    s.add_argument("--bursts", type=fraction, default=0.0, help="fraction of samples inside disturbance bursts")
    s.add_argument("--effect", action="append", default=[], metavar="NAME:param=value,...",
                   help="add an effect of the library (repeatable); `--list-effects` shows them")
    s.add_argument("--list-effects", action="store_true", help="list the effect library and exit")
    s.add_argument("--seed", type=nonneg_int, default=0)
    s.add_argument("--out", type=writable_path, help="output recording (.csv or .csv.gz); an existing file is "
                                                     "refused unless --force")
    s.add_argument("--force", action="store_true", help="overwrite an existing --out file")
    s.set_defaults(func=cmd_simulate)

    d = subparsers.add_parser("diagnose", help="diagnose the sim-to-real gap of a recording")
    d.add_argument("recording", type=input_file, help="recording CSV (docs/spec/recording.md); 'demo' for the bundled one")
    add_json_option(d)
    d.add_argument("--report", metavar="DIR", type=writable_dir, help="write report.md and PNG plots into DIR")
    d.add_argument("--exclude", action="append", default=[], metavar="EFFECT",
                   help="leave an effect out of the library (repeatable)")
    d.add_argument("--profile", default="fast", choices=("fast", "full"),
                   help="fast: <= 60 s for 10^4 samples; full: more replicas and bootstraps, all samples (slower)")
    d.add_argument("--replicas", type=int_range(2, 1000), help="replicas per model, 2..1000 (default: by profile)")
    d.add_argument("--seed", type=nonneg_int, default=0)
    g = d.add_argument_group("attitude-aided part (recordings with qw, qx, qy, qz)")
    g.add_argument("--no-attitude", dest="attitude", action="store_false",
                   help="skip the vector baseline from the recording's attitude")
    g.add_argument("--lat", type=float_range(-90.0, 90.0), help="latitude (deg) for the Earth-field model when the "
                   "recording has no GPS position (else a unit field with the inclination estimated)")
    g.add_argument("--lon", type=float_range(-180.0, 360.0), help="longitude (deg)")
    g.add_argument("--date", help="date for the Earth-field model (YYYY-MM-DD or a decimal year), default the recording's")
    add_quiet_option(d)
    d.add_argument("--verbose", action="store_true", help="print progress")
    d.set_defaults(func=cmd_diagnose)


def _check_effect(name, params):
    """Every parameter finite, and within the hard limits above (ValueError with the reason)."""
    import math

    for key, value in params.items():
        if not math.isfinite(value):
            raise ValueError(f"effect parameter {key!r} of {name}: {value!r} is not a finite number")
        lo, hi, what, lo_open = EFFECT_LIMITS.get((name, key), (None, None, "", False))
        if lo is None and key in NONNEGATIVE_PARAMS:
            lo, what = 0.0, "a scale, >= 0"
        if (lo is not None and (value < lo or (lo_open and value == lo))) or (hi is not None and value >= hi):
            raise ValueError(f"effect parameter {key!r} of {name}: {value:g} is out of range ({what})")


def _list_effects(out):
    from ..sim.effects import EFFECTS

    for e in EFFECTS.values():
        params = ", ".join(f"{p.name}={p.typical:g} {p.unit}" for p in e.params)
        needs = f" (needs {', '.join(e.needs)})" if e.needs else ""
        print(f"{e.name:24s} {e.doc}{needs}\n{'':24s} {params}", file=out)


def cmd_simulate(args) -> int:
    import numpy as np

    from ..sim import SensorModel, generate, parse_effect, simulate
    from .argtypes import check_new_output

    if args.list_effects:
        _list_effects(sys.stdout)
        return EXIT_OK
    if not args.out:
        raise UsageError("simulate needs --out FILE.csv")
    try:
        effects = [parse_effect(e) for e in args.effect]
        for name, params in effects:
            _check_effect(name, params)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    if args.trajectory.startswith("recording:"):
        from ..sim import from_recording

        path = args.trajectory.split(":", 1)[1]
        check_new_output(args.out, args.force, inputs=[path])
        rec = load_recording(path)
        try:
            traj = from_recording(rec)
        except ValueError as exc:
            raise UsageError(f"cannot use {path} as a trajectory: {exc}") from exc
    elif args.trajectory in TRAJECTORIES:
        check_new_output(args.out, args.force)
        n = args.duration * args.rate
        if n > MAX_SIM_SAMPLES:
            raise UsageError(f"--duration {args.duration:g} s at --rate {args.rate:g} Hz is {n:,.0f} samples; "
                             f"simulate makes at most {MAX_SIM_SAMPLES:,} (about 2 KB of memory each)")
        traj = generate(args.trajectory, duration=args.duration, rate=args.rate, seed=args.seed,
                        temp=None if args.temp == "none" else args.temp, power=args.power,
                        other_loads=not args.no_other_loads)
    else:
        raise UsageError(f"unknown trajectory {args.trajectory!r}; use {', '.join(TRAJECTORIES)} or recording:PATH")
    sensor = SensorModel(field=args.field, hard_iron=tuple(args.hard_iron), noise=args.noise, lsb=args.lsb,
                         burst_fraction=args.bursts)
    try:
        sim = simulate(traj, sensor, effects=effects, seed=args.seed + 1)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    rec = sim.recording
    # the last line of defence: a recording that is not one is refused, not written with exit 0
    if len(rec) < 2:
        raise UsageError(f"the simulation kept {len(rec)} sample(s) of {len(sim.keep)}; nothing written")
    if not (np.all(np.isfinite(rec.mag)) and np.all(np.isfinite(rec.t))):
        raise UsageError("the simulation produced non-finite magnetometer values or times; nothing written")
    outputs = Outputs()
    outputs.attempt(args.out, rec.write, args.out)
    if outputs.failed:
        return outputs.done(EXIT_OK)
    names = ", ".join(n for n, _ in effects) or "none"
    print(f"mkc-stream simulate: {len(rec)} samples, trajectory {traj.name}, effects: {names} -> {args.out}")
    return EXIT_OK


def _bad_rows_note(rec) -> str:
    """What the reader skipped, for a message about what was left."""
    if not rec.bad_rows:
        return ""
    line, why = rec.bad_rows[0]
    return f" ({len(rec.bad_rows)} bad rows were skipped while reading, first at line {line}: {why})"


def cmd_diagnose(args) -> int:
    from ..diagnose import DiagnoseError, diagnose
    from ..diagnose import report

    if (args.lat is None) != (args.lon is None):
        raise UsageError("--lat and --lon go together")
    if args.date is not None:
        from ..flight.earthfield import decimal_year

        try:
            decimal_year(args.date)
        except ValueError as exc:           # MKCInputError is a ValueError
            raise UsageError(f"--date: {exc}") from exc
    rec = load_recording(args.recording)
    out = sys.stderr if args.json == "-" else sys.stdout
    log = (lambda s: print(s, file=sys.stderr)) if args.verbose else None
    try:
        diag = diagnose(rec, exclude=args.exclude, profile=args.profile, replicas=args.replicas, seed=args.seed,
                        log=log, attitude=args.attitude, lat=args.lat, lon=args.lon, date=args.date)
    except (DiagnoseError, ValueError) as exc:
        raise UsageError(f"{args.recording}: {_diagnose_reason(exc)}{_bad_rows_note(rec)}") from exc
    if rec.bad_rows:
        diag.info["bad_rows"] = len(rec.bad_rows)
    if not args.quiet:
        print(report.text(diag, str(args.recording)), file=out)
        if rec.bad_rows:
            print(f"  ({len(rec.bad_rows)} bad rows were skipped while reading, first at line "
                  f"{rec.bad_rows[0][0]})", file=out)
    outputs = Outputs()
    if args.json:             # the result first: the report directory cannot take it with it
        obj = diag.to_json()
        obj["recording"] = str(args.recording)
        outputs.attempt(args.json, write_json, obj, args.json)
    if args.report:
        paths = outputs.attempt(args.report, report.write, diag, args.report, str(args.recording))
        if paths and not args.quiet:
            print(f"  report: {', '.join(str(p) for p in paths)}", file=out)
    return outputs.done(EXIT_OK if diag.verdict in ("no_gap", "explained") else EXIT_REJECTED)


def _diagnose_reason(exc) -> str:
    """numpy's bare "Singular matrix" says nothing about the recording: name the likely cause."""
    import numpy as np

    if isinstance(exc, np.linalg.LinAlgError):
        return (f"the calibration model cannot be fitted ({exc}): the recording does not span the sphere "
                "(a rotation about one axis, or a plane of directions)")
    return str(exc)
