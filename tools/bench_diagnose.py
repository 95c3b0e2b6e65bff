#!/usr/bin/env python
"""Time and memory of the sim-to-real diagnosis (run on demand; targets live here, not in unit tests).

    python tools/bench_diagnose.py                                   # 10^4, 10^5, 10^6 samples; hand, flight
    python tools/bench_diagnose.py --sizes 10000 --kinds hand --repeats 3
    python tools/bench_diagnose.py --sizes 1000000 --kinds flight --profile full --no-cli
    python tools/bench_diagnose.py --recording REC.csv --sizes ''   # only a recording file
    python tools/bench_diagnose.py --json out/bench_diagnose.json

Each case runs in a fresh Python process, so its peak memory is its own:
  - the recording: simulated with `mkc_stream.sim` (`generate(kind, duration, rate, seed,
    power=True)`, `simulate(traj, SensorModel(noise=0.1 uT, burst_fraction=0.01))`, no effect
    unless --effect; duration = samples / rate) or read from --recording; its seconds are reported
    apart. A null recording usually ends at "no_gap" before the attribution; --effect times the
    path where a gap is attributed
  - `diagnose(recording, profile=...)` alone: wall seconds (time.perf_counter), the verdict,
    the held-out gap index before and after the selected effects, its alarm level and the
    decimation the profile used
  - peak resident memory of the process (ru_maxrss of the child from os.wait4, MB = 2^20 bytes),
    and the resident memory just before `diagnose` (after the recording was built);
    --tracemalloc also reports the peak of Python and numpy allocations traced during
    `diagnose` (tracing slows the run, so its seconds are not comparable then)
  - the 1-minute load average (os.getloadavg, what `uptime` prints) before and after each case:
    other work on the machine lengthens the wall time
  - the command line end to end on the largest simulated case (first kind; --cli-kinds) written to a file
    (`mkc-stream diagnose FILE --json OUT`: reading the file is part of what a user waits
    for); the seconds to write that file are reported apart

Targets (docs/diagnosis.md, profile fast, 2 cores): 10^4 samples <= 60 s, 10^6 samples <= 300 s.
Rates: "auto" simulates 50 Hz below 10^6 samples and 1000 Hz from 10^6 (1000 s at 1 kHz).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

MB = 2.0 ** 20
#: ru_maxrss is in kilobytes on Linux, in bytes on macOS
_MAXRSS_BYTES = 1 if sys.platform == "darwin" else 1024
TARGET_S = {10_000: 60.0, 1_000_000: 300.0}      # profile fast, 2 cores


def auto_rate(n: int) -> float:
    """Hz: 50 below 10^6 samples, 1000 from 10^6 (a long log is a fast one)."""
    return 1000.0 if n >= 1_000_000 else 50.0


def _peak_rss_mb() -> float:
    """This process's own peak resident memory: VmHWM of /proc/self/status (its memory map's
    high-water mark, which starts afresh at exec). ru_maxrss is not that on Linux: exec carries the
    high-water mark of the process that started it (a 600 MB pytest worker's child reports 600 MB);
    it is the fallback where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024 / MB
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * _MAXRSS_BYTES / MB


def _current_rss_mb() -> float:
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / MB
    except (OSError, ValueError, IndexError):
        return float("nan")


def simulated_recording(kind: str, n: int, rate: float, seed: int = 1, effect: str | None = None):
    """A recording of n samples along a generated trajectory (see the module docstring); effect:
    ``"NAME:param=value,..."`` injects one effect of the library (a gap makes the attribution run)."""
    from mkc_stream.sim import SensorModel, generate, parse_effect, simulate

    traj = generate(kind, duration=n / rate, rate=rate, seed=seed, power=True)
    effects = [parse_effect(effect)] if effect else []
    return simulate(traj, SensorModel(noise=0.1, burst_fraction=0.01), effects=effects, seed=seed + 1000).recording


def measure(case: dict) -> dict:
    """Build one case's recording and diagnose it in this process; the figures of one table row.

    case: {"kind", "n", "rate", "seed"} for a simulated recording or {"path"} for a file, and
    "profile" ("fast" or "full"); optional "replicas" (default: by profile) and "tracemalloc".
    """
    t0 = time.perf_counter()
    import mkc_stream.diagnose as dg
    import_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    if case.get("path"):
        from mkc_stream.commands.common import load_recording

        rec = load_recording(case["path"])
    else:
        rec = simulated_recording(case["kind"], int(case["n"]), float(case["rate"]), int(case.get("seed", 1)),
                                  case.get("effect"))
    build_s = time.perf_counter() - t0
    rss_before = _current_rss_mb()
    peak_before = _peak_rss_mb()

    traced = None
    if case.get("tracemalloc"):
        import tracemalloc
        tracemalloc.start()
    t0 = time.perf_counter()
    d = dg.diagnose(rec, profile=case.get("profile", "fast"), replicas=case.get("replicas"))
    diagnose_s = time.perf_counter() - t0
    if case.get("tracemalloc"):
        traced = tracemalloc.get_traced_memory()[1] / MB
        tracemalloc.stop()
    return {
        "samples": int(len(rec.t)), "duration_s": float(rec.t[-1] - rec.t[0]),
        "import_s": import_s, "build_s": build_s, "diagnose_s": diagnose_s,
        "rss_before_diagnose_mb": rss_before, "peak_rss_before_diagnose_mb": peak_before,
        "peak_rss_mb": _peak_rss_mb(), "tracemalloc_peak_mb": traced,
        "verdict": d.verdict, "gap_before": float(d.gap_before), "gap_after": float(d.gap_after),
        "alarm": float(d.threshold), "selected": list(d.selected),
        "decimation": int(d.info["decimation"]), "samples_used": int(d.info["samples"]),
        "replicas": int(d.info["replicas"]),
        "where": [f"{w['family']}/{w['channel']}/{w['bin']} z {w['z']:.1f}" for w in d.where[:3]],
    }


def _mkc_stream_command() -> list:
    exe = shutil.which("mkc-stream", path=str(pathlib.Path(sys.executable).parent)) or shutil.which("mkc-stream")
    return [exe] if exe else [sys.executable, "-m", "mkc_stream"]


def _run_child(cmd: list, timeout: float, max_memory_mb: float | None = None) -> tuple:
    """(exit code, or None when killed at the timeout; stdout; wall s; peak RSS MB of that child).

    The peak is the child's ru_maxrss from wait4. On Linux it is at least the resident memory of this
    process when the child started (exec carries that high-water mark), so this process stays small
    (it imports neither numpy nor the package); the child's own measurement (_peak_rss_mb) is the
    one reported when it ran to the end.

    max_memory_mb: the child's address-space limit (RLIMIT_AS), so that a case too large for a
    shared machine ends in a MemoryError instead of pushing the others out."""
    def limit():
        cap = int(max_memory_mb * MB)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        p = subprocess.Popen(cmd, stdout=out, stderr=err, preexec_fn=limit if max_memory_mb else None)
        timed_out = False
        while True:
            pid, status, ru = os.wait4(p.pid, os.WNOHANG)      # wait4: this child's own rusage
            if pid:
                break
            if time.perf_counter() - t0 > timeout:
                p.kill()
                _, status, ru = os.wait4(p.pid, 0)
                timed_out = True
                break
            time.sleep(0.05)
        wall = time.perf_counter() - t0
        code = None if timed_out else os.waitstatus_to_exitcode(status)
        p.returncode = -9 if code is None else code         # reaped here: Popen must not wait again
        out.seek(0)
        err.seek(0)
        text, etext = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    if code not in (None, 0):
        sys.stderr.write(etext[-2000:])
        text += "\n" + json.dumps({"error": etext.strip().splitlines()[-1] if etext.strip() else ""})
    return code, text, wall, ru.ru_maxrss * _MAXRSS_BYTES / MB


def run_case(case: dict, timeout: float, max_memory_mb: float | None = None) -> dict:
    """One case in a fresh process, with the load average before and after."""
    load0 = os.getloadavg()[0]
    code, text, wall, rss = _run_child([sys.executable, __file__, "--child", json.dumps(case)], timeout,
                                       max_memory_mb)
    row = {**case, "load_before": load0, "load_after": os.getloadavg()[0], "child_wall_s": wall,
           "child_peak_rss_mb": rss, "status": "ok"}
    if code != 0:
        row["peak_rss_mb"] = rss          # up to the kill or the failure
    if code is None:
        row["status"] = f"timed out after {timeout:g} s"
    elif code != 0:
        row["status"] = f"failed (exit {code}): {json.loads(text.strip().splitlines()[-1])['error'][:120]}"
    else:
        row.update(json.loads(text.strip().splitlines()[-1]))
    return row


def run_cli(kind: str, n: int, rate: float, seed: int, effect: str | None, profile: str, timeout: float,
            workdir: pathlib.Path) -> dict:
    """`mkc-stream diagnose FILE --json OUT` end to end on a simulated recording written to a file."""
    path = workdir / f"{kind}_{n}.csv"
    t0 = time.perf_counter()
    simulated_recording(kind, n, rate, seed, effect).write(path)
    write_s = time.perf_counter() - t0
    out = workdir / f"{kind}_{n}.json"
    load0 = os.getloadavg()[0]
    code, _, wall, rss = _run_child(_mkc_stream_command() + ["diagnose", str(path), "--json", str(out),
                                                             "--profile", profile, "--quiet"], timeout)
    row = {"kind": kind, "n": n, "rate": rate, "effect": effect, "profile": profile, "path": "cli", "write_s": write_s,
           "file_mb": path.stat().st_size / MB, "cli_s": wall, "peak_rss_mb": rss, "exit_code": code,
           "load_before": load0, "load_after": os.getloadavg()[0], "status": "ok"}
    if code is None:
        row["status"] = f"timed out after {timeout:g} s"
    elif code in (0, 1) and out.exists():
        obj = json.loads(out.read_text())
        row.update(verdict=obj["verdict"], gap_before=obj["gap_before"], gap_after=obj["gap_after"],
                   alarm=obj["threshold"], decimation=obj["info"]["decimation"],
                   diagnose_s=obj["info"]["seconds"])
    else:
        row["status"] = f"failed (exit {code})"
    path.unlink(missing_ok=True)
    return row


def _median(rows, key):
    xs = [r[key] for r in rows if isinstance(r.get(key), (int, float))]
    return statistics.median(xs) if xs else None


def summarise(rows: list) -> dict:
    """Repeats of one case merged: medians of the seconds and memory, every verdict."""
    first = rows[0]
    keys = ("build_s", "diagnose_s", "peak_rss_mb", "rss_before_diagnose_mb", "tracemalloc_peak_mb",
            "gap_before", "gap_after", "alarm")
    out = {**first, **{k: _median(rows, k) for k in keys}}
    out["diagnose_s_all"] = [r.get("diagnose_s") for r in rows]
    out["verdicts"] = [r.get("verdict") for r in rows]
    out["load_before"] = max(r["load_before"] for r in rows)
    out["load_after"] = max(r["load_after"] for r in rows)
    out["status"] = ", ".join(sorted({r["status"] for r in rows}))
    return out


def _fmt(x, nd=1):
    return "-" if x is None else f"{x:.{nd}f}" if isinstance(x, float) else str(x)


def table(rows: list, cli: list) -> str:
    head = ("| samples | kind | rate Hz | profile | decimation | build s | diagnose s | target s | peak RSS MB "
            "| RSS before diagnose MB | verdict | gap before -> after (alarm) | load 1-min before/after | status |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        name = (r.get("kind") or pathlib.Path(r.get("path", "")).name) + (f" + {r['effect']}" if r.get("effect") else "")
        runs = r.get("diagnose_s_all") or [r.get("diagnose_s")]
        secs = _fmt(r.get("diagnose_s")) + ("" if len(runs) < 2 else f" (runs {', '.join(_fmt(s) for s in runs)})")
        target = TARGET_S.get(r.get("samples", r.get("n"))) if r.get("profile") == "fast" else None
        verdict = r.get("verdict") if len(set(r.get("verdicts") or [None])) < 2 else "/".join(r["verdicts"])
        lines.append(
            f"| {r.get('samples', r.get('n'))} | {name} | {_fmt(r.get('rate'), 0)} | {r.get('profile')} "
            f"| {_fmt(r.get('decimation'))} | {_fmt(r.get('build_s'))} | {secs} | {_fmt(target, 0)} "
            f"| {_fmt(r.get('peak_rss_mb'), 0)} | {_fmt(r.get('rss_before_diagnose_mb'), 0)} | {_fmt(verdict)} "
            f"| {_fmt(r.get('gap_before'), 2)} -> {_fmt(r.get('gap_after'), 2)} ({_fmt(r.get('alarm'), 2)}) "
            f"| {_fmt(r['load_before'], 2)} / {_fmt(r['load_after'], 2)} | {r['status']} |")
    if cli:
        lines += ["", "| command line | samples | file MB | write s (not timed below) | `mkc-stream diagnose` s "
                      "| of which diagnose s | peak RSS MB | verdict | exit | load 1-min before/after | status |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in cli:
            lines.append(
                f"| {r['kind']} {r['profile']} | {r['n']} | {_fmt(r['file_mb'])} | {_fmt(r['write_s'])} "
                f"| {_fmt(r['cli_s'])} | {_fmt(r.get('diagnose_s'))} | {_fmt(r['peak_rss_mb'], 0)} "
                f"| {_fmt(r.get('verdict'))} | {_fmt(r.get('exit_code'))} "
                f"| {_fmt(r['load_before'], 2)} / {_fmt(r['load_after'], 2)} | {r['status']} |")
    return "\n".join(lines)


def _ints(text):
    return [int(float(x)) for x in text.split(",") if x.strip()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,100000,1000000", help="samples per recording, comma separated")
    ap.add_argument("--kinds", default="hand,flight", help="trajectory kinds (hand, figure8, flight)")
    ap.add_argument("--rates", default="auto", help="Hz, comma separated (each size at each rate), or 'auto'")
    ap.add_argument("--seed", type=int, default=1, help="seed of the simulated recordings")
    ap.add_argument("--effect", help="inject one effect, NAME:param=value,... (default: none, a null recording)")
    ap.add_argument("--repeats", type=int, default=1, help="fresh processes per case (median reported)")
    ap.add_argument("--profile", default="fast", choices=("fast", "full"))
    ap.add_argument("--recording", action="append", default=[], metavar="PATH", help="also a recording file")
    ap.add_argument("--no-cli", action="store_true", help="skip the command line on the largest case")
    ap.add_argument("--cli-kinds", help="kinds to run the command line on (default: the first of --kinds)")
    ap.add_argument("--tracemalloc", action="store_true", help="also trace allocations (slows the run)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per case before it is killed")
    ap.add_argument("--max-memory-mb", type=float, help="address-space limit per case (MB); over it, a MemoryError")
    ap.add_argument("--json", metavar="PATH", help="write every row as JSON")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(json.loads(args.child))))
        return 0
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")

    cases = []
    for n in _ints(args.sizes):
        rates = [auto_rate(n)] if args.rates == "auto" else [float(r) for r in args.rates.split(",")]
        for kind in [k.strip() for k in args.kinds.split(",") if k.strip()]:
            for rate in rates:
                cases.append({"kind": kind, "n": n, "rate": rate, "seed": args.seed, "effect": args.effect})
    cases += [{"path": str(pathlib.Path(p).resolve())} for p in args.recording]
    rows = []
    for case in cases:
        case = {**case, "profile": args.profile, "tracemalloc": args.tracemalloc}
        reps = [run_case(case, args.timeout, args.max_memory_mb) for _ in range(args.repeats)]
        rows.append(summarise(reps))
        print(f"  {rows[-1].get('kind') or case.get('path')} {rows[-1].get('samples', case.get('n'))}: "
              f"diagnose {_fmt(rows[-1].get('diagnose_s'))} s, peak {_fmt(rows[-1].get('peak_rss_mb'), 0)} MB, "
              f"{rows[-1].get('verdict')} ({rows[-1]['status']})", file=sys.stderr, flush=True)
    cli = []
    simulated = [c for c in cases if "n" in c]
    if simulated and not args.no_cli:
        n = max(c["n"] for c in simulated)
        kinds = (args.cli_kinds or simulated[0]["kind"]).split(",")
        with tempfile.TemporaryDirectory() as tmp:
            for c in (c for c in simulated if c["n"] == n and c["kind"] in kinds):
                cli.append(run_cli(c["kind"], n, c["rate"], c["seed"], c["effect"], args.profile, args.timeout, pathlib.Path(tmp)))
                print(f"  cli {c['kind']} {n}: {_fmt(cli[-1]['cli_s'])} s ({cli[-1]['status']})",
                      file=sys.stderr, flush=True)
    print(table(rows, cli))
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps({"cases": rows, "cli": cli, "cores": os.cpu_count()},
                                                      indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
