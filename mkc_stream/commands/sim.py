"""`simulate` (a recording from the sensor simulator) and `diagnose` (the sim-to-real gap)."""
from __future__ import annotations

import sys

TRAJECTORIES = ("hand", "figure8", "flight")


def register(subparsers):
    s = subparsers.add_parser("simulate", help="simulate a magnetometer/IMU recording with effects")
    s.add_argument("--trajectory", default="hand",
                   help="hand, figure8, flight, or recording:PATH to replay a recording's times, directions and aux")
    s.add_argument("--duration", type=float, default=200.0, help="seconds (generated trajectories)")
    s.add_argument("--rate", type=float, default=50.0, help="samples per second (generated trajectories)")
    s.add_argument("--temp", default="cycle", choices=("cycle", "ramp", "const", "none"), help="temperature profile")
    s.add_argument("--power", action="store_true", help="add flight-like throttle, current and voltage columns")
    s.add_argument("--no-other-loads", action="store_true", help="current follows throttle only")
    s.add_argument("--field", type=float, default=50.0, help="field strength, uT")
    s.add_argument("--noise", type=float, default=0.1, help="white noise per axis, uT RMS")
    s.add_argument("--hard-iron", default="12,-7,20", help="b as x,y,z in uT")
    s.add_argument("--lsb", type=float, default=0.0, help="output resolution, uT (0 = continuous)")
    s.add_argument("--bursts", type=float, default=0.0, help="fraction of samples inside disturbance bursts")
    s.add_argument("--effect", action="append", default=[], metavar="NAME:param=value,...",
                   help="add an effect of the library (repeatable); `--list-effects` shows them")
    s.add_argument("--list-effects", action="store_true", help="list the effect library and exit")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", help="output recording (.csv or .csv.gz)")
    s.set_defaults(func=cmd_simulate)

    d = subparsers.add_parser("diagnose", help="diagnose the sim-to-real gap of a recording")
    d.add_argument("recording", help="recording CSV (spec/recording.md); 'demo' for the bundled one")
    d.add_argument("--json", metavar="PATH", help="write the machine-readable result ('-' for stdout)")
    d.add_argument("--report", metavar="DIR", help="write report.md and PNG plots into DIR")
    d.add_argument("--exclude", action="append", default=[], metavar="EFFECT",
                   help="leave an effect out of the library (repeatable)")
    d.add_argument("--profile", default="fast", choices=("fast", "full"),
                   help="fast: <= 60 s for 10^4 samples; full: more replicas and bootstraps, all samples (slower)")
    d.add_argument("--replicas", type=int, help="replicas per model (default: by profile)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--quiet", action="store_true", help="no human report")
    d.add_argument("--verbose", action="store_true", help="print progress")
    d.set_defaults(func=cmd_diagnose)


def _list_effects(out):
    from ..sim.effects import EFFECTS

    for e in EFFECTS.values():
        params = ", ".join(f"{p.name}={p.typical:g} {p.unit}" for p in e.params)
        needs = f" (needs {', '.join(e.needs)})" if e.needs else ""
        print(f"{e.name:24s} {e.doc}{needs}\n{'':24s} {params}", file=out)


def cmd_simulate(args) -> int:
    from ..cli import EXIT_OK, UsageError
    from ..sim import SensorModel, generate, parse_effect, simulate

    if args.list_effects:
        _list_effects(sys.stdout)
        return EXIT_OK
    if not args.out:
        raise UsageError("simulate needs --out FILE.csv")
    try:
        effects = [parse_effect(e) for e in args.effect]
        b = tuple(float(x) for x in args.hard_iron.split(","))
        if len(b) != 3:
            raise ValueError("--hard-iron needs three numbers x,y,z")
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    if args.trajectory.startswith("recording:"):
        from ..io.recording import RecordingError, read_recording
        from ..sim import from_recording

        path = args.trajectory.split(":", 1)[1]
        try:
            rec = read_recording(path)
            traj = from_recording(rec)
        except (OSError, RecordingError, ValueError) as exc:
            raise UsageError(f"cannot use {path} as a trajectory: {exc}") from exc
    elif args.trajectory in TRAJECTORIES:
        if not (args.duration > 0 and args.rate > 0):
            raise UsageError("--duration and --rate must be positive")
        traj = generate(args.trajectory, duration=args.duration, rate=args.rate, seed=args.seed,
                        temp=None if args.temp == "none" else args.temp, power=args.power,
                        other_loads=not args.no_other_loads)
    else:
        raise UsageError(f"unknown trajectory {args.trajectory!r}; use {', '.join(TRAJECTORIES)} or recording:PATH")
    sensor = SensorModel(field=args.field, hard_iron=b, noise=args.noise, lsb=args.lsb, burst_fraction=args.bursts)
    try:
        sim = simulate(traj, sensor, effects=effects, seed=args.seed + 1)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    sim.recording.write(args.out)
    names = ", ".join(n for n, _ in effects) or "none"
    print(f"mkc-stream simulate: {len(sim.recording)} samples, trajectory {traj.name}, effects: {names} -> {args.out}")
    return EXIT_OK


def cmd_diagnose(args) -> int:
    from ..cli import EXIT_OK, EXIT_REJECTED, UsageError, write_json
    from ..diagnose import DiagnoseError, diagnose
    from ..diagnose import report
    from ..io.recording import RecordingError, read_recording

    try:
        rec = read_recording(args.recording)
    except (OSError, RecordingError) as exc:
        raise UsageError(f"cannot read {args.recording}: {exc}") from exc
    out = sys.stderr if args.json == "-" else sys.stdout
    log = (lambda s: print(s, file=sys.stderr)) if args.verbose else None
    try:
        diag = diagnose(rec, exclude=args.exclude, profile=args.profile, replicas=args.replicas, seed=args.seed,
                        log=log)
    except (DiagnoseError, ValueError) as exc:
        raise UsageError(f"{args.recording}: {exc}") from exc
    if rec.bad_rows:
        diag.info["bad_rows"] = len(rec.bad_rows)
    if not args.quiet:
        print(report.text(diag, str(args.recording)), file=out)
        if rec.bad_rows:
            print(f"  ({len(rec.bad_rows)} bad rows were skipped while reading, first at line "
                  f"{rec.bad_rows[0][0]})", file=out)
    if args.report:
        paths = report.write(diag, args.report, str(args.recording))
        if not args.quiet:
            print(f"  report: {', '.join(str(p) for p in paths)}", file=out)
    if args.json:
        obj = diag.to_json()
        obj["recording"] = str(args.recording)
        write_json(obj, args.json)
    return EXIT_OK if diag.verdict in ("no_gap", "explained") else EXIT_REJECTED
