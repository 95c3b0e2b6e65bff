#!/usr/bin/env python
"""The diagnosis's false-alarm rate on families of null recordings.

    python tools/null_suite.py [--families indep,hand,...] [--per-family N] [--seed S] [--jobs J]
                               [--out DIR] [--samples N] [--max FAMILY=N ...]

Runs :func:`mkc_stream.diagnose.diagnose` (what ``mkc-stream diagnose`` runs, fast profile) on
each recording of each family and reports per family: recordings, false alarms, the effects
claimed, and seconds per diagnosis (median, max). Writes ``DIR/null_suite.json`` and
``DIR/null_suite.md`` after every recording, so an interrupted run keeps what it measured.

A false alarm is any verdict other than ``no_gap`` on a null recording. A ``baseline_rejected``
verdict (the calibrator would not accept the baseline calibration: too little of the sphere)
says nothing about effects; there the verdict on what could still be tested
(``info.scope.verdict_on_testable``) is the one counted, and the rejections are counted apart.

Families (null: nothing the diagnosis lists as an effect):

* ``indep``: tools/indep_sim.py, a simulator written independently of mkc_stream.sim, 10^4 samples.
* ``hand``, ``figure8``, ``flight``: mkc_stream.sim along a generated trajectory of that kind
  with the ``mkc-stream simulate`` defaults (50 Hz, white noise 0.1 uT, no rounding, no bursts)
  plus temperature and flight-power aux columns (``--temp cycle --power``), 10^4 samples.
* ``hand-1e3``, ``hand-1e5``: the same for hand at 10^3 and 10^5 samples (the diagnosis
  decimates 10^5 to 2 x 10^4 in its fast profile).
* ``ground``, ``static``: the same along a ground vehicle's trajectory (turns about the vertical
  only: a circle of directions) and at rest in one attitude (one direction), 10^4 samples;
  ``ground-1e3``, ``ground-1e5`` at 10^3 and 10^5 samples. Neither determines an ellipsoid:
  every baseline should be rejected, and what is counted is the verdict on what could still be
  tested (not part of the default run).
* ``sweep``: mkc_stream.sim.presets.sweep (the synthetic calibration stream: no accelerometer,
  disturbance bursts, which the baseline models), 10^4 samples.
* ``hand-noisy`` (white noise 0.6 uT, 1.2% of the field), ``hand-aniso`` (0.1, 0.05, 0.1 uT per
  axis), ``indep-quiet`` (a quarter of the drawn noise), ``indep-iso`` (the same noise on every
  axis): one setting changed, to tell which alarms follow the noise rather than the simulator
  (not part of the default run).
* ``hand-10hz``, ``hand-1khz``: hand at another output rate, 10^4 samples (not part of the
  default run).
* ``real``: the undisturbed real recordings bundled with the package and in tests/data. They
  are not nulls (real noise is neither white nor Gaussian); reported for what they give. The
  cave-survey recordings (24 samples each) are listed as not diagnosed (too short).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import sys
import time
from collections import Counter

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

#: family -> (kind, samples); kind "indep", a trajectory of mkc_stream.sim, "sweep" or "real"
FAMILIES = {
    "indep": ("indep", 10_000),
    "hand": ("hand", 10_000),
    "figure8": ("figure8", 10_000),
    "flight": ("flight", 10_000),
    "hand-1e3": ("hand", 1_000),
    "hand-1e5": ("hand", 100_000),
    "ground": ("ground", 10_000),
    "static": ("static", 10_000),
    "ground-1e3": ("ground", 1_000),
    "ground-1e5": ("ground", 100_000),
    "sweep": ("sweep", 10_000),
    "real": ("real", None),
    "hand-noisy": ("hand", 10_000),
    "indep-quiet": ("indep", 10_000),
    "indep-iso": ("indep", 10_000),
    "hand-aniso": ("hand", 10_000),
    "hand-10hz": ("hand", 10_000),
    "hand-1khz": ("hand", 10_000),
}
#: families that change one setting to tell which alarms follow it: our simulator with the white
#: noise at 1.2% of the field (0.6 uT at 50 uT) or unequal per axis (uT); the independent one with
#: a quarter of its noise, or with the same noise on every axis (the RMS of its drawn levels)
SENSOR_NOISE_UT = {"hand-noisy": 0.6, "hand-aniso": (0.1, 0.05, 0.1)}
INDEP_OPTIONS = {"indep-quiet": {"noise_scale": 0.25}, "indep-iso": {"isotropic_noise": True}}
SIM_RATE_HZ = 50.0
#: families at another output rate (Hz): 10^4 samples are 1000 s at 10 Hz, 10 s at 1 kHz
RATE_HZ = {"hand-10hz": 10.0, "hand-1khz": 1000.0}
NULL_VERDICT = "no_gap"


def real_recordings():
    """[(name, loader)] of the undisturbed real recordings shipped with the package and tests."""
    from mkc_stream.io import datasets
    from mkc_stream.io.recording import bundled_recording

    data = ROOT / "tests" / "data"
    out = [("qmc5883l noisy (bundled)", lambda: bundled_recording("qmc5883l_noisy.csv")),
           ("qmc5883l filtered", lambda: datasets.load_qmc5883l_csv(data / "qmc5883l-tomisuarez" /
                                                                    "filtered_raw_data.csv")),
           ("ck-explorer acc+mag", lambda: datasets.load_ck_explorer_csv(data / "ck-explorer-accmag" /
                                                                         "acc_mag_log.csv"))]
    for f in sorted((data / "mag-cal-cave-survey").glob("*.json")):
        out.append((f"cave-survey {f.stem}", lambda f=f: datasets.load_cave_survey_json(f)))
    return out


def make_recording(family: str, index: int, seed: int, samples: int | None = None):
    """(name, Recording, drawn) of recording ``index`` of a family; ``samples`` overrides its
    length; drawn: what the independent simulator drew that bears on the diagnosis (else {})."""
    kind, n = FAMILIES[family]
    n = samples or n
    s = seed + 1000 * index
    if kind == "indep":
        from indep_sim import simulate_null

        rec, truth = simulate_null(n, s, **INDEP_OPTIONS.get(family, {}))
        sig = truth["noise_uT"]
        drawn = {"noise_over_field": float(np.sqrt(np.mean(sig ** 2)) / truth["field_uT"]),
                 "noise_max_over_min": float(sig.max() / sig.min()),
                 "odr_hz": truth["odr_hz"], "rate_sd_rad_s": truth["rate_sd_rad_s"],
                 "linear_acc_m_s2": truth["linear_acc_m_s2"]}
        return f"indep seed {s}", rec, drawn
    if kind == "sweep":
        from mkc_stream.sim.presets import sweep

        return f"sweep seed {s}", sweep(seed=s, N=n).recording, {}
    if kind == "real":
        name, load = real_recordings()[index]
        return name, load(), {}
    from mkc_stream.sim import SensorModel, generate, simulate

    # the `mkc-stream simulate --trajectory KIND --power` defaults (sensor seed = seed + 1 as there)
    rate = RATE_HZ.get(family, SIM_RATE_HZ)
    traj = generate(kind, duration=n / rate, rate=rate, seed=s, temp="cycle", power=True)
    sensor = SensorModel(noise=SENSOR_NOISE_UT.get(family, SensorModel.noise))
    return f"{kind} seed {s}", simulate(traj, sensor, seed=s + 1).recording, {}


def family_size(family: str, per_family: int) -> int:
    return len(real_recordings()) if FAMILIES[family][0] == "real" else per_family


def run_one(job):
    """Diagnose one recording; a dict of what the report needs (errors are reported, not raised)."""
    from mkc_stream.diagnose import DiagnoseError, diagnose

    family, index, seed, samples = job
    row = {"family": family, "index": index}
    try:
        name, rec, drawn = make_recording(family, index, seed, samples)
    except Exception as exc:  # noqa: BLE001 - a recording that cannot be made is reported
        return {**row, "name": f"#{index}", "error": f"cannot make the recording: {exc}"}
    row.update(name=name, samples=len(rec), **({"drawn": drawn} if drawn else {}))
    t0 = time.perf_counter()
    try:
        d = diagnose(rec, profile="fast", seed=0)
    except DiagnoseError as exc:
        return {**row, "error": f"not diagnosed: {exc}", "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    scope = d.info.get("scope", {}) or {}
    calibration = d.info["baseline"]["calibration"]
    accepted = bool(calibration["accepted"])
    rejection = calibration.get("rejection") or {}
    on_testable = scope.get("verdict_on_testable") or d.verdict
    counted = d.verdict if accepted else on_testable
    mt = d.info.get("matched_tests", {})
    return {**row, "seconds": seconds, "verdict": d.verdict, "verdict_on_testable": on_testable,
            "baseline_accepted": accepted, "false_alarm": counted != NULL_VERDICT,
            # the calibrator's failed checks (calib.acceptance.CHECKS) or its code, when rejected
            "rejected_for": None if accepted else "+".join(rejection.get("failed") or [rejection.get("code", "?")]),
            "rejection_reason": None if accepted else calibration.get("reason"),
            "gap_before": _num(d.gap_before), "gap_after": _num(d.gap_after), "alarm": _num(d.threshold),
            "detected_by": d.info.get("detected_by"), "matched_fired": list(mt.get("fired", [])),
            "selected": list(d.selected), "ambiguous_with": list(d.ambiguous_with),
            "where": d.where[:3], "decimation": d.info.get("decimation")}


def _num(x):
    x = float(x)
    return x if np.isfinite(x) else None


def summarise(rows):
    """Per family: recordings, diagnosed, false alarms, rejections, claimed effects, seconds."""
    out = {}
    for fam in dict.fromkeys(r["family"] for r in rows):
        rs = [r for r in rows if r["family"] == fam]
        ok = [r for r in rs if "error" not in r]
        secs = [r["seconds"] for r in ok]
        claimed = Counter(e for r in ok if r["false_alarm"] for e in (r["selected"] or ["(none selected)"]))
        fa = [r for r in ok if r["false_alarm"]]
        out[fam] = {
            "recordings": len(rs), "diagnosed": len(ok), "errors": len(rs) - len(ok),
            "false_alarms": len(fa), "false_alarm_rate": len(fa) / len(ok) if ok else None,
            "baseline_rejected": sum(not r["baseline_accepted"] for r in ok),
            "rejected_for": dict(Counter(r["rejected_for"] for r in ok if r.get("rejected_for"))),
            "verdicts": dict(Counter(r["verdict"] for r in ok)),
            "detected_by": dict(Counter(r["detected_by"] for r in fa)),
            "claimed_effects": dict(claimed),
            "matched_fired": dict(Counter(t for r in fa for t in r["matched_fired"])),
            "seconds_median": statistics.median(secs) if secs else None,
            "seconds_max": max(secs) if secs else None,
            "samples": sorted({r["samples"] for r in rs if "samples" in r}),
        }
    return out


def markdown(summary, rows) -> str:
    lines = ["| family | samples | recordings | false alarms | rate | baseline rejected | claimed effects "
             "| s/diagnosis median | max |", "|---|---|---|---|---|---|---|---|---|"]
    for fam, s in summary.items():
        rate = "-" if s["false_alarm_rate"] is None else f"{s['false_alarm_rate']:.0%}"
        claimed = ", ".join(f"{k} x{v}" for k, v in s["claimed_effects"].items()) or "-"
        n = ", ".join(f"{x:g}" for x in s["samples"])
        sec = "-" if s["seconds_median"] is None else f"{s['seconds_median']:.1f}"
        smax = "-" if s["seconds_max"] is None else f"{s['seconds_max']:.1f}"
        err = f" ({s['errors']} not diagnosed)" if s["errors"] else ""
        lines.append(f"| {fam} | {n} | {s['diagnosed']}{err} | {s['false_alarms']} | {rate} | "
                     f"{s['baseline_rejected']} | {claimed} | {sec} | {smax} |")
    rejected = {fam: s["rejected_for"] for fam, s in summary.items() if s.get("rejected_for")}
    if rejected:
        lines += ["", "Baselines rejected, by the calibrator's failed checks:", ""]
        lines += [f"- {fam}: " + ", ".join(f"{k} x{v}" for k, v in why.items()) for fam, why in rejected.items()]
    alarms = [r for r in rows if r.get("false_alarm") or "error" in r]
    if alarms:
        lines += ["", "Alarms and errors (gap index before -> after, alarm level):", ""]
        for r in alarms:
            if "error" in r:
                lines.append(f"- {r['family']} {r['name']}: {r['error']}")
                continue
            lines.append(f"- {r['family']} {r['name']}: {r['verdict']}"
                         + ("" if r["baseline_accepted"] else f" (on what could be tested: {r['verdict_on_testable']})")
                         + f", detected by {r['detected_by']}, gap {_fmt(r['gap_before'])} -> {_fmt(r['gap_after'])}"
                         f", alarm {_fmt(r['alarm'])}, selected {r['selected'] or '-'}"
                         + (f", matched tests fired {r['matched_fired']}" if r["matched_fired"] else "")
                         + (f", white noise / field {r['drawn']['noise_over_field']:.2%}, largest / smallest"
                            f" axis noise {r['drawn']['noise_max_over_min']:.2f}" if r.get("drawn") else "")
                         + (f", largest gap {r['where'][0]['family']}/{r['where'][0]['channel']}/"
                            f"{r['where'][0]['bin']} z {r['where'][0]['z']:.1f}" if r["where"] else ""))
    return "\n".join(lines) + "\n"


def _fmt(x):
    return "-" if x is None else f"{x:.3f}"


def write(out: pathlib.Path, rows, args):
    summary = summarise(rows)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"config": args, "summary": summary, "recordings": rows}
    (out / "null_suite.json").write_text(json.dumps(doc, indent=1, default=_jsonable))
    (out / "null_suite.md").write_text(markdown(summary, rows))
    return summary


def _jsonable(x):
    if isinstance(x, (np.integer, np.floating, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON: {type(x).__name__}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--families", default="indep,hand,figure8,flight,hand-1e3,hand-1e5,sweep,real",
                    help=f"comma-separated, of {', '.join(FAMILIES)}")
    ap.add_argument("--per-family", type=int, default=20, help="recordings per simulated family")
    ap.add_argument("--max", action="append", default=[], metavar="FAMILY=N",
                    help="fewer recordings for one family (e.g. hand-1e5=5; repeatable)")
    ap.add_argument("--samples", type=int, help="override every simulated family's length (quick checks)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--out", default="null_suite_out", help="directory for null_suite.json and .md")
    a = ap.parse_args(argv)
    fams = [f.strip() for f in a.families.split(",") if f.strip()]
    unknown = [f for f in fams if f not in FAMILIES]
    if unknown:
        ap.error(f"unknown families {unknown}; use {', '.join(FAMILIES)}")
    if a.per_family < 1 or a.jobs < 1:
        ap.error("--per-family and --jobs must be at least 1")
    caps = {}
    for item in a.max:
        name, _, n = item.partition("=")
        if name not in FAMILIES or not n.isdigit():
            ap.error(f"--max takes FAMILY=N, got {item!r}")
        caps[name] = int(n)
    jobs = [(f, i, a.seed, a.samples if FAMILIES[f][0] != "real" else None)
            for f in fams for i in range(min(family_size(f, a.per_family), caps.get(f, a.per_family)
                                             if FAMILIES[f][0] != "real" else 10**9))]
    out = pathlib.Path(a.out)
    rows = []
    config = vars(a)

    def done(row):
        rows.append(row)
        what = row.get("error") or (f"{row['verdict']}{'' if row['baseline_accepted'] else ' / ' + row['verdict_on_testable']}"
                                   f" gap {_fmt(row['gap_before'])} alarm {_fmt(row['alarm'])}"
                                   f" selected {row['selected'] or '-'}")
        print(f"[{len(rows)}/{len(jobs)}] {row['family']} {row['name']}: {what} "
              f"({row.get('seconds', float('nan')):.1f} s)", flush=True)
        write(out, rows, config)

    if a.jobs == 1:
        for job in jobs:
            done(run_one(job))
    else:
        from multiprocessing import get_context

        with get_context("spawn").Pool(a.jobs) as pool:
            for row in pool.imap(run_one, jobs):
                done(row)
    summary = write(out, rows, config)
    print(markdown(summary, rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
