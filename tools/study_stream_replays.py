#!/usr/bin/env python
"""Does the streamed calibration depend on where the stream starts, its rate, or each window's noise?

    python tools/study_stream_replays.py                          # BROAD 03 and 26, window 512
    python tools/study_stream_replays.py --window 256 --option switching=latest

Each BROAD trial (tools/broad_truth.py: a known distortion applied to the dataset's calibrated
field, heading from the motion capture) is replayed through MagCalibrator in 0.2 s chunks, whole,
without its first 1, 10, 50 or 100 samples, and at half the rate (even and odd samples). Reported
per replay, for the ACCEPTED calibration:
  - changes: how many times the accepted calibration changed over the run;
  - final / worst: |b - b_ref| at the end and its largest value after the first acceptance (uT),
    against b_ref = the least-squares fit of the trial's known-clean samples ("floor") and against
    the distortion's true hard iron ("truth", which includes the dataset's own residual offset);
  - heading: the RMS heading error against the motion capture (deg), beside the floor's;
  - |db|: how far its final hard iron lies from the whole-stream replay's (uT);
  - sd: its reported hard-iron standard deviation (uT) and heading sd (deg);
  - restarts: how many times a new calibration replaced the accepted one outright (the first
    acceptance, a switch, or a restart of the pool), as opposed to a trial joining the pool.
A developer tool run on demand; nothing here tunes the calibrator.
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from broad_truth import Case, heading_error_rms  # noqa: E402

from mkc_stream.calib.fit import fit_ellipsoid  # noqa: E402
from mkc_stream.calib.streaming import MagCalibrator  # noqa: E402

CHUNK_S = 0.2


def replay(raw, case, refs, window, estep_every, options):
    """The accepted calibration's path over one replay: (calibrator, {ref: [|b - b_ref| per change]})."""
    cal = MagCalibrator(window=window, estep_every=estep_every, keep_history=False, **options)
    chunk = max(1, int(CHUNK_S * case.trial["fs"]))
    path = {k: [] for k in refs}
    prev = None
    for s in range(0, len(raw), chunk):
        cal.learn_many(raw[s:s + chunk])
        if cal.accepted is not None and cal.accepted is not prev:
            prev = cal.accepted
            for k, b in refs.items():
                path[k].append(float(np.linalg.norm(prev.hard_iron - b)))
    return cal, path


def study(root, key, window, estep_every, options, log):
    c = Case(root, key)
    floor = fit_ellipsoid(c.raw[c.clean], "ls")
    refs = {"floor": floor.hard_iron, "truth": c.b_true}
    head_floor = heading_error_rms(floor.hard_iron, floor.soft_iron, c.raw_all, c.trial, c.rows)
    log(f"trial {key}: {len(c.raw)} samples at {c.trial['fs']:.1f} Hz; floor heading {head_floor:.3f} deg")
    log("  replay     changes  final/worst vs floor  final/worst vs truth  heading  |db|   sd (uT)              "
        "heading sd  restarts")
    rows, base = [], None
    replays = [("whole", c.raw)] + [(f"drop {k}", c.raw[k:]) for k in (1, 10, 50, 100)] + \
        [("half even", c.raw[::2]), ("half odd", c.raw[1::2])]
    for label, raw in replays:
        cal, path = replay(raw, c, refs, window, estep_every, options)
        acc = cal.accepted
        if acc is None:
            log(f"  {label:10s} never accepted: {cal.status_reason()}")
            rows.append({"trial": key, "replay": label, "accepted": False})
            continue
        base = acc.hard_iron if base is None else base
        head = heading_error_rms(acc.hard_iron, acc.soft_iron, c.raw_all, c.trial, c.rows)
        db = float(np.linalg.norm(acc.hard_iron - base))
        u = acc.uncertainty
        log(f"  {label:10s} {len(path['floor']):7d}  {path['floor'][-1]:6.3f} / {max(path['floor']):6.3f}"
            f"       {path['truth'][-1]:6.3f} / {max(path['truth']):6.3f}       {head:6.3f}  {db:5.3f}  "
            f"{np.round(u['hard_iron_sd'], 3)}  {u['heading_sd_deg']:.3f}  {cal.switches}")
        rows.append({"trial": key, "replay": label, "accepted": True, "changes": len(path["floor"]),
                     "final_vs_floor": path["floor"][-1], "worst_vs_floor": max(path["floor"]),
                     "final_vs_truth": path["truth"][-1], "worst_vs_truth": max(path["truth"]),
                     "heading_deg": head, "floor_heading_deg": head_floor, "db_vs_whole": db,
                     "uncertainty": u, "restarts": cal.switches})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default=str(REPO.parent / "shared" / "data" / "broad"))
    ap.add_argument("--trial", default="03,26")
    ap.add_argument("--window", type=int, default=512)
    ap.add_argument("--estep-every", type=int, default=32)
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a MagCalibrator keyword, e.g. --option switching=latest")
    args = ap.parse_args(argv)
    options = dict(kv.split("=", 1) for kv in args.option)
    log = lambda s="": print(s, flush=True)  # noqa: E731
    log(f"MagCalibrator window {args.window}, E-step every {args.estep_every}, options {options or 'none'}")
    for key in args.trial.split(","):
        study(args.data_root, key, args.window, args.estep_every, options, log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
