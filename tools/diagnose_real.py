#!/usr/bin/env python
"""Run the sim-to-real gap diagnosis on the real recordings of the shared data directory.

    python tools/diagnose_real.py [--data DIR] [--out DIR] [--profile fast|full] [--reports]

DIR defaults to the ``shared/data`` directory beside the repository. For each recording it
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--out", help="write one JSON (and with --reports a report directory) per recording")
    ap.add_argument("--profile", default="fast", choices=("fast", "full"))
    ap.add_argument("--reports", action="store_true")
    ap.add_argument("--only", help="substring of the recordings to run")
    a = ap.parse_args(argv)
    data = pathlib.Path(a.data)
    out = pathlib.Path(a.out) if a.out else None
    for name, load in sources(data):
        if a.only and a.only not in name:
            continue
        try:
            rec = load()
        except Exception as exc:  # noqa: BLE001 - report and go on
            print(f"{name}: cannot load ({exc})")
            continue
        t0 = time.perf_counter()
        try:
            d = diagnose(rec, profile=a.profile)
        except DiagnoseError as exc:
            print(f"{name}: {len(rec)} samples - not diagnosed: {exc}")
            continue
        sec = time.perf_counter() - t0
        print(f"\n=== {name} ({len(rec)} samples, {sec:.0f} s)")
        print(report.text(d, name))
        if out:
            out.mkdir(parents=True, exist_ok=True)
            slug = name.replace(" ", "_").replace("/", "_")
            obj = d.to_json()
            obj["recording"] = name
            (out / f"{slug}.json").write_text(json.dumps(obj, indent=1))
            if a.reports:
                report.write(d, out / slug, name)


if __name__ == "__main__":
    main()
