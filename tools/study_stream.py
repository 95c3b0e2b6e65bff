#!/usr/bin/env python
"""Accuracy of the streaming magnetometer calibrator, beside batch fits and peers.

    python tools/study_stream.py                       # 20 seeds x {0, 10, 25 %} bursts + BROAD
    python tools/study_stream.py --seeds 5 --no-peers  # quicker
    python tools/study_stream.py --window 512 --estep-every 32 --json out/study_stream.json

A developer tool run on demand (tests/test_stream_accuracy.py runs a fixed subset). Nothing here
tunes the calibrator: it runs with the given window/K and its defaults.

Synthetic streams: synthetic_mag(seed=3000+i (--seed-base), N=3000 at 50 Hz = 60 s of hand-held sweeping,
field 50 uT, noise 0.3 uT, hard iron up to +-30 uT, soft iron eigenvalues within e^+-0.25) with
phone-like bursts: constant 5-40 uT offsets lasting 20-60 samples (0.4-1.2 s) covering 0, 10 or
25 % of the samples. The same seeds at every fraction (paired: only the bursts differ).

Each stream is fed to MagCalibrator in 0.2 s chunks (as a live source would); reported from its
final *accepted* calibration:
  - hard-iron error |b - b_true| (uT), soft-iron error ||S - S_true||_F;
  - heading error: the compass-swing deviation, i.e. the largest error of the tilt-free heading
    atan2(-y, x) of S (m_raw - b) over a full turn of a level device in a field of 50 uT and 60 deg
    inclination (degrees);
  - time to the first accepted calibration (s), and whether any calibration was accepted.
Beside it, on the whole 60 s recording: batch least squares ("ls"), batch MKC-EM, and the peer
tools of tools/study_ellipsoid.py when installed (`pip install -e ".[bench]"`).

Real data: the BROAD trials (already calibrated imu_mag, real disturbances kept) with a known
synthetic distortion raw = S_true^-1 m + b_true on top; errors against (b_true, S_true), and
against what batch MKC-EM of the undistorted data implies (the dataset's own residual offset).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from mkc_stream.calib.fit import fit_ellipsoid  # noqa: E402
from mkc_stream.calib.streaming import MagCalibrator  # noqa: E402
from mkc_stream.calib.synthetic import random_soft_iron, synthetic_mag  # noqa: E402

RATE_HZ = 50.0
INCLINATION_DEG = 60.0
BROAD_B_TRUE = np.array([12.0, -30.0, 8.0])
BROAD_SEED = 20261121


def heading_error_deg(b, S, b_true, S_true, field=50.0, inclination_deg=INCLINATION_DEG, steps=360):
    """Largest heading error (deg) over a full turn of a level device (compass swing)."""
    inc = np.radians(inclination_deg)
    psi = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    # the field in the frame of a level device with heading psi (x forward, y left, z up)
    u = np.stack([np.cos(inc) * np.cos(psi), -np.cos(inc) * np.sin(psi), -np.sin(inc) * np.ones_like(psi)], axis=1)
    raw = (field * u) @ np.linalg.inv(S_true).T + b_true
    cal = (raw - b) @ np.asarray(S).T
    est = np.arctan2(-cal[:, 1], cal[:, 0])
    err = np.angle(np.exp(1j * (est - psi)))
    return float(np.degrees(np.abs(err).max()))


STREAM_OPTIONS: dict = {}     # --option key=value: StreamConfig fields, for ablations


def stream_calibrate(raw, window, estep_every, chunk=int(0.2 * RATE_HZ)):
    cal = MagCalibrator(window=window, estep_every=estep_every, keep_history=False, **STREAM_OPTIONS)
    t0 = time.perf_counter()
    for s in range(0, len(raw), chunk):
        cal.learn_many(raw[s:s + chunk])
    elapsed = time.perf_counter() - t0
    return cal, elapsed


def errors(b, S, b_true, S_true):
    return {"hard_iron_err": float(np.linalg.norm(b - b_true)),
            "soft_iron_err": float(np.linalg.norm(S - S_true)),
            "heading_err_deg": heading_error_deg(b, S, b_true, S_true)}


def peer_methods(enabled):
    if not enabled:
        return {}
    try:
        import study_ellipsoid as se
    except Exception:   # noqa: BLE001 - the peers are optional
        return {}
    methods, _ = se.discover_methods()
    return {name: runner for name, (kind, runner) in methods.items() if kind == "peer"}


def synthetic_study(seeds, fractions, N, window, estep_every, peers, log, seed_base=3000):
    rows = []
    for frac in fractions:
        for seed in range(seed_base, seed_base + seeds):
            syn = synthetic_mag(seed=seed, N=N, burst_fraction=frac, rate_hz=RATE_HZ)
            cal, elapsed = stream_calibrate(syn.raw, window, estep_every)
            row = {"fraction": frac, "seed": seed, "samples_per_s": N / elapsed}
            acc = cal.accepted
            if acc is None:
                row["stream"] = {"accepted": False, "reason": cal.status_reason()}
            else:
                row["stream"] = {"accepted": True, "first_accepted_s": cal.first_accepted_at / RATE_HZ,
                                 **errors(acc.hard_iron, acc.soft_iron, syn.hard_iron, syn.soft_iron)}
            for name in ("ls", "mkc-em"):
                f = fit_ellipsoid(syn.raw, name)
                row[name] = errors(f.hard_iron, f.soft_iron, syn.hard_iron, syn.soft_iron)
            for name, runner in peers.items():
                try:
                    b, S, F, _ = runner(syn.raw)
                    row[name] = errors(b, S, syn.hard_iron, syn.soft_iron)
                except Exception as e:   # noqa: BLE001 - a peer's failure is a result, recorded
                    row[name] = {"failed": f"{type(e).__name__}: {e}"}
            rows.append(row)
            s = row["stream"]
            log(f"  bursts {frac:4.0%} seed {seed}: stream "
                + (f"b err {s['hard_iron_err']:.3f} uT, heading {s['heading_err_deg']:.2f} deg, "
                   f"first accepted {s['first_accepted_s']:.1f} s" if s["accepted"] else f"NOT accepted ({s['reason']})")
                + f"; batch ls {row['ls']['hard_iron_err']:.3f}, mkc-em {row['mkc-em']['hard_iron_err']:.3f}")
    return rows


def summarise(rows, fractions, methods):
    out = {}
    for frac in fractions:
        sel = [r for r in rows if r["fraction"] == frac]
        out[frac] = {}
        for m in methods:
            ok = [r[m] for r in sel if m in r and r[m].get("accepted", True) and "failed" not in r[m]]
            entry = {"runs": len(sel), "ok": len(ok)}
            for key in ("hard_iron_err", "soft_iron_err", "heading_err_deg", "first_accepted_s"):
                v = np.array([o[key] for o in ok if key in o])
                if len(v):
                    entry[key] = {"mean": float(v.mean()), "median": float(np.median(v)),
                                  "p90": float(np.percentile(v, 90)), "max": float(v.max())}
            out[frac][m] = entry
    return out


def broad_study(root, window, estep_every, log):
    results = []
    for name in ("26_disturbed_phone_vibration_A.mat", "03_undisturbed_slow_rotation_C.hdf5"):
        p = root / "broad" / name
        if not p.exists():
            log(f"  BROAD {name}: not found under {root}; skipped")
            continue
        from mkc_stream.io.recording import load_broad

        m = load_broad(p).mag
        S_true = random_soft_iron(np.random.default_rng(BROAD_SEED), 0.25)
        raw = m @ np.linalg.inv(S_true).T + BROAD_B_TRUE
        # What the dataset's own calibration leaves: batch MKC-EM on the undistorted data, mapped
        # through the distortion (b0 -> S_true^-1 b0 + b_true, S0 -> S0 S_true, det-normalised).
        f0 = fit_ellipsoid(m, "mkc-em")
        b_floor = np.linalg.solve(S_true, f0.hard_iron) + BROAD_B_TRUE
        cal, elapsed = stream_calibrate(raw, window, estep_every)
        rate = float(load_broad(p).meta.get("rate_hz", 0) or 0) or None
        row = {"trial": name, "samples": len(m), "stream_samples_per_s": len(m) / elapsed}
        acc = cal.accepted
        if acc is None:
            row["stream"] = {"accepted": False, "reason": cal.status_reason()}
        else:
            row["stream"] = {"accepted": True, "first_accepted_samples": cal.first_accepted_at,
                             "first_accepted_s": cal.first_accepted_at / rate if rate else None,
                             **errors(acc.hard_iron, acc.soft_iron, BROAD_B_TRUE, S_true),
                             "hard_iron_err_vs_floor": float(np.linalg.norm(acc.hard_iron - b_floor))}
        for meth in ("ls", "mkc-em"):
            f = fit_ellipsoid(raw, meth)
            row[meth] = {**errors(f.hard_iron, f.soft_iron, BROAD_B_TRUE, S_true),
                         "hard_iron_err_vs_floor": float(np.linalg.norm(f.hard_iron - b_floor))}
        results.append(row)
        s = row["stream"]
        log(f"  BROAD {name}: " + (f"stream b err vs truth {s['hard_iron_err']:.3f} uT, vs floor "
                                   f"{s['hard_iron_err_vs_floor']:.3f} uT, heading {s['heading_err_deg']:.2f} deg"
                                   if s["accepted"] else f"stream NOT accepted ({s['reason']})")
            + f"; batch mkc-em vs floor {row['mkc-em']['hard_iron_err_vs_floor']:.3f} uT")
    return results


def print_table(summary, fractions, methods, log):
    log("\nhard-iron error |b - b_true| (uT) mean / median / p90 / max; heading error (deg) median / max; "
        "time to first acceptance (s) median / max")
    for frac in fractions:
        log(f"\nbursts {frac:.0%}")
        for m in methods:
            e = summary[frac].get(m)
            if not e or "hard_iron_err" not in e:
                log(f"  {m:22s} no successful runs ({e['ok'] if e else 0}/{e['runs'] if e else 0})")
                continue
            h, g = e["hard_iron_err"], e["heading_err_deg"]
            line = (f"  {m:22s} ok {e['ok']:2d}/{e['runs']:2d}  b {h['mean']:7.3f} {h['median']:7.3f} {h['p90']:7.3f} "
                    f"{h['max']:7.3f}"
                    f"   heading {g['median']:6.2f} {g['max']:6.2f}")
            if "first_accepted_s" in e:
                fa = e["first_accepted_s"]
                line += f"   first accepted {fa['median']:5.1f} {fa['max']:5.1f}"
            log(line)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--seed-base", type=int, default=3000, help="first seed of the synthetic streams")
    ap.add_argument("--fractions", default="0,0.1,0.25")
    ap.add_argument("--samples", type=int, default=3000, help="stream length (50 Hz)")
    ap.add_argument("--window", type=int, default=512)
    ap.add_argument("--estep-every", type=int, default=32)
    ap.add_argument("--no-peers", action="store_true")
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--data-root", default=str(REPO.parent / "shared" / "data"))
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a StreamConfig field for an ablation, e.g. --option fp_rounds=2")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args(argv)
    for kv in args.option:
        k, v = kv.split("=", 1)
        try:
            STREAM_OPTIONS[k] = float(v) if "." in v or "e" in v else int(v)
        except ValueError:
            STREAM_OPTIONS[k] = v           # a word: switching=latest, policy=fifo
    fractions = [float(f) for f in args.fractions.split(",")]
    log = lambda s="": print(s, flush=True)  # noqa: E731
    peers = peer_methods(not args.no_peers)
    # compile first so the first stream's timing is not the compiler's
    stream_calibrate(synthetic_mag(seed=1, N=1000).raw, args.window, args.estep_every)
    log(f"streaming calibrator W = {args.window}, K = {args.estep_every}; {args.seeds} seeds from {args.seed_base}; "
        f"peers: {', '.join(peers) or 'none installed'}")
    rows = synthetic_study(args.seeds, fractions, args.samples, args.window, args.estep_every, peers, log,
                           args.seed_base)
    methods = ["stream", "ls", "mkc-em", *peers]
    summary = summarise(rows, fractions, methods)
    print_table(summary, fractions, methods, log)
    broad = [] if args.no_real else broad_study(pathlib.Path(args.data_root), args.window, args.estep_every, log)
    rate = np.median([r["samples_per_s"] for r in rows])
    log(f"\nMagCalibrator throughput (0.2 s chunks, median over streams): {rate:,.0f} samples/s")
    if args.json:
        out = pathlib.Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"config": vars(args), "runs": rows,
                                   "summary": {str(k): v for k, v in summary.items()}, "broad": broad},
                                  indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
