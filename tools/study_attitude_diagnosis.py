"""Study: the attitude-aided part of the diagnosis (mkc_stream/diagnose/attitude.py) on simulated flights
with known current coefficients, and on the real logs that carry an attitude.

Simulated flights (mkc_stream.flight.simulated.simulated_flight, 300 s at 25 Hz, the field given as the
truth's NED vector, 3 deg RMS wandering yaw error, 0.3 deg tilt error, white noise 0.1 uT, current
0.6-35 A with other loads switching, and a logged temperature with no effect: add_temperature): NULLS flights with K = 0 (seeds 1000..), EFFECTS flights with K
drawn per axis with |K_i| in 0.02-0.5 uT/A and random signs, delay 30 ms (seeds 2000..). Per flight:
which effects were found, the current's fitted K with its 95% interval, whether the interval holds the
truth, the error |K - K_true| (uT/A), the held-out share of variance explained, and the seconds.
Summary: false detections on the nulls (any effect found), detections and interval coverage (per axis)
on the effect flights.

--unit-field: the flights without a field reference (fit_flight's unit-field mode, the inclination
estimated), as a log without GPS. --logs PATH ...: also the attitude-aided diagnosis of each compass of each flight log or bag (the log's
GPS position for the field, else the unit-field mode), every effect's figures.

Run:  python tools/study_attitude_diagnosis.py --nulls 10 --effects 5 --json /tmp/h3/study.json \
          --logs ../shared/data/flightlog-dronekit-log171/log171.bin
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings

import numpy as np


def add_temperature(rec, seed):
    """A logged board temperature with no effect on the field: a warm-up of 5 degC (90 s time constant), a
    slow wander of 0.3 degC (60 s) and 0.05 degC of noise (so the temperature test has a null too)."""
    from mkc_stream.sim.effects.noise import gauss_markov

    rng = np.random.default_rng(seed + 7919)
    t = rec.t - rec.t[0]
    rec.aux["temp"] = (25.0 + 5.0 * (1.0 - np.exp(-t / 90.0)) + gauss_markov(rng, t, 0.3, 60.0, dims=1)[:, 0]
                       + rng.normal(0.0, 0.05, t.shape))


def sim_run(seed, K, given_field=True):
    from mkc_stream.diagnose.attitude import diagnose_attitude
    from mkc_stream.flight.simulated import simulated_flight

    sf = simulated_flight(seed=seed, k_current=tuple(K))
    add_temperature(sf.recording, seed)
    t0 = time.perf_counter()
    ad = diagnose_attitude(sf.recording, earth=sf.truth["h_ned"] if given_field else None)
    sec = time.perf_counter() - t0
    e = ad.test("current_hard_iron")
    val, ci = np.array(e.size["value"]), np.array(e.size["ci95"])
    K = np.asarray(K, dtype=np.float64)
    return {"seed": seed, "K_true": K.tolist(), "found": ad.found, "K": val.tolist(), "ci95": ci.tolist(),
            "covered": [bool(lo <= k <= hi) for k, (lo, hi) in zip(K, ci)],
            "error_uT_per_A": float(np.linalg.norm(val - K)), "p_value": e.p_value,
            "variance_explained": e.held_out["variance_explained"], "delay_s": e.to_json().get("delay_s"),
            **{n: {"found": ad.test(n).found, "p_value": ad.test(n).p_value,
                   "variance_explained": ad.test(n).held_out.get("variance_explained")}
               for n in ("throttle_hard_iron", "temperature_offset")},
            "ambiguous_with": ad.ambiguous, "seconds": sec}


def log_runs(path):
    from mkc_stream.diagnose.attitude import diagnose_attitude
    from mkc_stream.ingest.flightlogs import inspect_flight_log, read_flight_log

    out = []
    for inst in inspect_flight_log(path)["instances"]:
        rec = read_flight_log(f"{path}#instance={inst['id']}")
        t0 = time.perf_counter()
        ad = diagnose_attitude(rec)
        obj = ad.to_json()
        obj.update(recording=str(path), instance=inst["id"], topic=inst.get("topic"), rows=len(rec),
                   seconds=time.perf_counter() - t0)
        out.append(obj)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nulls", type=int, default=10)
    ap.add_argument("--effects", type=int, default=5)
    ap.add_argument("--logs", nargs="*", default=[])
    ap.add_argument("--unit-field", action="store_true",
                    help="give the flights no field: the unit-field mode (inclination estimated; slower)")
    ap.add_argument("--json", help="write every run's figures here")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore", UserWarning)
    rng = np.random.default_rng(7)
    given = not a.unit_field
    nulls = [sim_run(1000 + s, (0.0, 0.0, 0.0), given) for s in range(a.nulls)]
    effects = []
    for s in range(a.effects):
        K = rng.uniform(0.02, 0.5, 3) * rng.choice([-1.0, 1.0], 3)
        effects.append(sim_run(2000 + s, K, given))
    for tag, runs in (("null", nulls), ("K != 0", effects)):
        for r in runs:
            print(f"{tag:6s} seed {r['seed']}: found {r['found'] or 'none'}; K {np.round(r['K'], 3).tolist()} "
                  f"(true {np.round(r['K_true'], 3).tolist()}), interval holds it {r['covered']}, "
                  f"|err| {r['error_uT_per_A']:.3f} uT/A, p {r['p_value']:.2g}, held-out explained "
                  f"{r['variance_explained']:.3f}, delay {r['delay_s']} s (true 0.03); temperature p "
                  f"{r['temperature_offset']['p_value']:.2g}, throttle p {r['throttle_hard_iron']['p_value']:.2g}; "
                  f"{r['seconds']:.1f} s")
    summary = {
        "nulls": len(nulls), "false_detections": sum(bool(r["found"]) for r in nulls),
        "false_detections_by_effect": {n: sum(n in r["found"] for r in nulls)
                                       for n in ("current_hard_iron", "throttle_hard_iron", "temperature_offset")},
        "temperature_found_on_effect_flights": sum("temperature_offset" in r["found"] for r in effects),
        "null_current_max_abs_uT_per_A": max((float(np.max(np.abs(r["K"]))) for r in nulls), default=None),
        "effects": len(effects), "detected": sum("current_hard_iron" in r["found"] for r in effects),
        "axis_coverage": f"{sum(sum(r['covered']) for r in effects)}/{3 * len(effects)}",
        "null_axis_coverage": f"{sum(sum(r['covered']) for r in nulls)}/{3 * len(nulls)}",
        "error_uT_per_A": [r["error_uT_per_A"] for r in effects],
        "seconds_median": float(np.median([r["seconds"] for r in nulls + effects])) if nulls + effects else None}
    print(json.dumps(summary, indent=1))
    logs = []
    for p in a.logs:
        for obj in log_runs(p):
            logs.append(obj)
            print(f"{obj['recording']} instance {obj['instance']} ({obj['topic']}, {obj['rows']} rows, "
                  f"{obj['seconds']:.1f} s): " + ("not run: " + obj["reason"] if not obj["ran"] else
                                                  f"found {obj['found'] or 'none'}"))
            for e in obj["effects"]:
                if e["testable"]:
                    print(f"   {e['name']:20s} found {e['found']!s:5s} p {e['p_value']:.2g} size "
                          f"{np.round(e['size']['value'], 3).tolist()} {e['size']['unit']} 95% "
                          f"{np.round(e['size']['ci95'], 3).tolist()} held-out explained "
                          f"{e['held_out']['variance_explained']:.3f} rms {np.round(e['held_out']['rms_before'], 2).tolist()}"
                          f" -> {np.round(e['held_out']['rms_after'], 2).tolist()} "
                          + " ".join(f"{k}={e[k]}" for k in ("delay_s", "lag_s") if k in e))
                else:
                    print(f"   {e['name']:20s} not testable: {e['reason']}")
            if obj.get("ambiguous_with"):
                print(f"   ambiguous: {obj['ambiguous_with']}")
    if a.json:
        with open(a.json, "w", encoding="utf-8") as f:
            json.dump({"summary": summary, "nulls": nulls, "effects": effects, "logs": logs}, f, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
