#!/usr/bin/env python
"""Run the sim-to-real gap diagnosis on the real recordings of the shared data directory.

    python tools/diagnose_real.py [--data DIR] [--out DIR] [--profile fast|full] [--reports] [--table MD]

DIR defaults to the ``shared/data`` directory beside the repository. The recordings are the
magnetometer sets and every magnetometer stream of its flight logs and bags. For each recording it
prints the verdict, the gap index before and after, the selected and ambiguous effects with
their magnitudes, and the largest gaps; with --out it writes one JSON per recording (and with
--reports the human report and plots).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mkc_stream.diagnose import DiagnoseError, diagnose, report  # noqa: E402
from mkc_stream.io import recording as R  # noqa: E402


def sources(data: pathlib.Path):
    q = data / "qmc5883l-tomisuarez"
    yield "qmc5883l noisy", lambda: R.load_qmc5883l_csv(q / "noisy_raw_data.csv")
    yield "qmc5883l filtered", lambda: R.load_qmc5883l_csv(q / "filtered_raw_data.csv")
    yield "ck-explorer acc+mag", lambda: R.load_ck_explorer_csv(data / "ck-explorer-accmag" / "acc_mag_log.csv")
    for f in sorted((data / "rasteiro-marg-robot").glob("*/*.mat")):
        yield f"rasteiro {f.parent.name} {f.stem}", (lambda f=f: R.load_rasteiro_mat(f))
    for f in sorted((data / "broad").glob("*.mat")) + sorted((data / "broad").glob("*.hdf5")):
        yield f"broad {f.stem}", (lambda f=f: R.load_broad(f))
    for f in sorted((data / "mag-cal-cave-survey").glob("*.json"))[:2]:
        yield f"cave-survey {f.stem}", (lambda f=f: R.load_cave_survey_json(f))
    yield from flight_logs(data)


def flight_logs(data: pathlib.Path):
    """Every magnetometer stream of the flight logs and bags (each instance of a log on its own)."""
    from mkc_stream.ingest.flightlogs import inspect_flight_log, is_flight_log, read_flight_log

    logs = [f for pattern in ("flightlog-*/*", "rosbag-*/*") for f in sorted(data.glob(pattern))
            if f.name != "SOURCE.txt" and is_flight_log(str(f))]
    for f in logs:
        try:
            ids = [inst["id"] for inst in inspect_flight_log(str(f))["instances"]]
        except Exception as exc:  # noqa: BLE001 - reported as a recording that cannot be loaded
            yield f"{f.parent.name}/{f.name}", (lambda exc=exc: (_ for _ in ()).throw(exc))
            continue
        for i in ids:
            path = f"{f}#instance={i}" if len(ids) > 1 else str(f)
            yield f"{f.parent.name}/{f.name}#{i}", (lambda path=path: read_flight_log(path))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--out", help="write one JSON (and with --reports a report directory) per recording")
    ap.add_argument("--profile", default="fast", choices=("fast", "full"))
    ap.add_argument("--reports", action="store_true")
    ap.add_argument("--only", help="substring of the recordings to run")
    ap.add_argument("--table", help="also write the summary as a markdown table to this path")
    a = ap.parse_args(argv)
    rows = []
    data = pathlib.Path(a.data)
    out = pathlib.Path(a.out) if a.out else None
    for name, load in sources(data):
        if a.only and a.only not in name:
            continue
        try:
            rec = load()
        except Exception as exc:  # noqa: BLE001 - report and go on
            print(f"{name}: cannot load ({exc})")
            rows.append((name, "", "", f"cannot load: {exc}", "", "", ""))
            continue
        t0 = time.perf_counter()
        try:
            d = diagnose(rec, profile=a.profile)
        except DiagnoseError as exc:
            print(f"{name}: {len(rec)} samples - not diagnosed: {exc}")
            rows.append((name, str(len(rec)), "", f"not diagnosed: {exc}", "", "", ""))
            continue
        sec = time.perf_counter() - t0
        print(f"\n=== {name} ({len(rec)} samples, {sec:.0f} s)")
        print(report.text(d, name))
        rows.append(summary_row(name, len(rec), sec, d))
        if out:
            out.mkdir(parents=True, exist_ok=True)
            slug = name.replace(" ", "_").replace("/", "_")
            obj = d.to_json()
            obj["recording"] = name
            (out / f"{slug}.json").write_text(json.dumps(obj, indent=1))
            if a.reports:
                report.write(d, out / slug, name)
    table = markdown_table(rows)
    print("\n" + table)
    if a.table:
        pathlib.Path(a.table).write_text(table + "\n")


def summary_row(name, n, sec, d):
    """name, samples, seconds, verdict, gap before -> after (alarm), selected effects with their
    magnitudes, and what was dropped as not testable."""
    sel = []
    for r in d.effects:
        if r.selected:
            mag = r.magnitude or {}
            value = mag.get("value")
            sel.append(f"{r.name} {_num(value)} {mag.get('unit', '')}".strip() if value is not None else r.name)
    gap = f"{d.gap_before:.2f}" + (f" -> {d.gap_after:.2f}" if d.selected else "") + f" ({d.threshold:.2f})"
    scope = (d.info.get("scope") or {}).get("verdict_on_testable")
    verdict = d.verdict + (f" (on what it can test: {scope})" if scope and d.verdict == "baseline_rejected" else "")
    return (name, str(n), f"{sec:.0f}", verdict, gap, "; ".join(sel) or "-", str(len(d.dropped)))


def _num(v):
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(f"{x:.3g}" for x in v) + "]"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def markdown_table(rows):
    head = ("recording", "samples", "s", "verdict", "gap index before -> after (alarm)", "selected effects", "dropped")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(c.replace("|", "/") for c in r) + " |" for r in rows]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
