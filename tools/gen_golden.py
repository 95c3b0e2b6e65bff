#!/usr/bin/env python
"""Golden vectors for the C port (firmware_ref/): the Python reference's state at every checkpoint.

    python tools/gen_golden.py                 # (re)write tests/data/golden/
    python tools/gen_golden.py --check         # regenerate in memory, compare with the stored files

Each vector is an input (a synthetic stream from its seed, a bundled real recording, or a
multi-channel linear stream; the input itself is NOT stored, only its definition and a digest)
and a configuration. For the magnetometer vectors MagCalibrator's feedback path (sphere fit, eigen-decompositions) is
bit-reproducible (mkc_stream/calib/portable.py, the C port's algorithms; firmware_ref/README.md
"Why portable feedback"); every checkpoint's
samples seen, E-steps, status, theta, sigma, d, a, normalisation (c0, s0), decision, reason and trial
calibration (b, S, F, quality) are stored, plus "anchors": the whole reference state at a few
checkpoints, from which tests/test_firmware.py restarts the float build (teacher forcing). For the
linear vectors StreamingMKC runs and each checkpoint's index, status, theta, sigma, d, a and
counters are stored.

Files: tests/data/golden/index.json (vectors, configurations, digests, tolerances, a libm
fingerprint) and one <name>.npz per vector. Regenerate after any change of the Python reference
(kernels/, calib/, state.py), last.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mkc_stream import firmware as FW  # noqa: E402

OUT = ROOT / "tests" / "data" / "golden"

MAG = "mag"
LINEAR = "linear"

#: (name, kind, source, configuration, replayable through mkc_replay's CSV path)
VECTORS = [
    ("syn_s1_b00", MAG, {"kind": "synthetic", "seed": 1, "N": 3000, "burst": 0.0}, {}, True),
    ("syn_s2_b10", MAG, {"kind": "synthetic", "seed": 2, "N": 3000, "burst": 0.10}, {}, True),
    ("syn_s3_b25", MAG, {"kind": "synthetic", "seed": 3, "N": 3000, "burst": 0.25}, {}, True),
    ("syn_s4_b10_w128_k16", MAG, {"kind": "synthetic", "seed": 4, "N": 4000, "burst": 0.10},
     {"window": 128, "estep_every": 16}, True),
    ("syn_s5_b25_fifo", MAG, {"kind": "synthetic", "seed": 5, "N": 2500, "burst": 0.25}, {"policy": "fifo"}, True),
    # gross isolated spikes (3% at ~1000 uT): the high-breakdown restarts (restart_at, cold_start_at)
    ("syn_s7_b10_spikes", MAG, {"kind": "synthetic", "seed": 7, "N": 3000, "burst": 0.10, "spikes": 0.03,
                                "spike_uT": 1000.0}, {}, True),
    # NaN samples reach the calibrator only in-process (a recording file's reader drops such rows)
    ("syn_s6_b10_nan", MAG, {"kind": "synthetic", "seed": 6, "N": 3000, "burst": 0.10,
                             "nan": [[1, 97, 5], [0, 251, 11]]}, {}, False),
    ("qmc5883l_filtered", MAG, {"kind": "qmc5883l", "path": "tests/data/qmc5883l-tomisuarez/filtered_raw_data.csv"},
     {}, True),
    ("qmc5883l_noisy_demo_w512", MAG, {"kind": "recording", "path": "mkc_stream/data/qmc5883l_noisy.csv"},
     {"window": 512}, True),
    ("ck_explorer", MAG, {"kind": "ck_explorer", "path": "tests/data/ck-explorer-accmag/acc_mag_log.csv"}, {}, True),
    ("broad_excerpt", MAG, {"kind": "broad", "path": "tests/data/broad/26_disturbed_phone_vibration_A_excerpt.mat"},
     {}, True),
    ("cave_survey_ab", MAG, {"kind": "cave_survey", "path": "tests/data/mag-cal-cave-survey/ab.json", "cycles": 4},
     {"window": 24, "estep_every": 4}, True),
    ("cave_survey_ee", MAG, {"kind": "cave_survey", "path": "tests/data/mag-cal-cave-survey/ee.json", "cycles": 4},
     {"window": 24, "estep_every": 4}, True),
    ("cave_survey_hj", MAG, {"kind": "cave_survey", "path": "tests/data/mag-cal-cave-survey/hj.json", "cycles": 4},
     {"window": 24, "estep_every": 4}, True),
    ("linear_s0_4x2_w64_k8", LINEAR, {"kind": "linear", "seed": 0, "T": 1500, "n": 4, "m": 2},
     {"window": 64, "estep_every": 8}, True),
    ("linear_s1_6x3_w256_k32", LINEAR, {"kind": "linear", "seed": 1, "T": 3000, "n": 6, "m": 3},
     {"window": 256, "estep_every": 32}, True),
    ("linear_s3_6x3_fp3_d05", LINEAR, {"kind": "linear", "seed": 3, "T": 2000, "n": 6, "m": 3},
     {"window": 128, "estep_every": 32, "fp_rounds": 3, "estep_max_iter": 5, "d": 0.5}, True),
]

MAG_DEFAULTS = {"window": 256, "estep_every": 32, "policy": "direction"}
ANCHORS_PER_VECTOR = 6


def libm_fingerprint() -> list:
    """libm results the vectors depend on (CPython's math calls the same libm as Numba and the C
    port): if they differ on a machine, its results differ in the last bits, and the chaotic sigma
    of the E-step makes the stream diverge - the tests skip the exact comparison then."""
    xs = [0.1234567891, -3.75, 12.5, -0.031, 700.2]
    out = []
    for x in xs:
        out += [math.exp(x).hex(), math.expm1(x).hex(), math.log1p(abs(x)).hex(), math.log(abs(x)).hex(),
                math.atan2(x, 1.7).hex()]
    return out


def mag_records(name, source, cfg):
    inp = FW.vector_input(source)
    mags = inp["mags"]
    full = dict(MAG_DEFAULTS, **cfg)
    recs, cal = FW.python_checkpoints(mags, full["window"], full["estep_every"], inp["unit"], capture_state=True,
                                      policy=full["policy"])
    K = len(recs)
    arr = {
        "samples_seen": np.array([r["samples_seen"] for r in recs], np.int64),
        "esteps": np.array([r["esteps"] for r in recs], np.int64),
        "status": np.array([r["status"] for r in recs], np.int64),
        "accepted": np.array([r["accepted"] for r in recs], bool),
        "has_trial": np.array([r["has_trial"] for r in recs], bool),
        "theta": np.array([r["theta"] for r in recs]).reshape(K, 9),
        "sigma": np.array([r["sigma"] for r in recs]), "d": np.array([r["d"] for r in recs]),
        "a": np.array([r["a"] for r in recs]), "c0s0": np.array([r["c0s0"] for r in recs]).reshape(K, 4),
    }
    nan = np.full
    arr["hard_iron"] = np.array([r["hard_iron"] if r["has_trial"] else nan(3, np.nan) for r in recs]).reshape(K, 3)
    arr["soft_iron"] = np.array([r["soft_iron"].ravel() if r["has_trial"] else nan(9, np.nan) for r in recs]).reshape(K, 9)
    arr["field"] = np.array([r["field"] if r["has_trial"] else np.nan for r in recs])
    arr["quality"] = np.array([r["quality"] if r["has_trial"] else nan(6, np.nan) for r in recs]).reshape(K, 6)
    arr["condition"] = np.array([r["condition"] if r["has_trial"] else np.nan for r in recs])
    arr["reasons"] = np.array([r["reason"] for r in recs], dtype=str)
    # anchors: reference states after the first normalisation (non-provisional) at evenly spaced
    # checkpoints, for the float build's teacher-forced comparison; only for streams without
    # rejected samples (the state's next_index is then the input position)
    anchors = []
    init = min(full["window"], 64)
    if np.isfinite(mags).all():
        eligible = [k for k in range(K - 1) if recs[k]["state"]["next_index"] >= init
                    and recs[k]["state"]["flags"][0] == 0]
        if eligible:
            pick = sorted({eligible[int(round(i))] for i in np.linspace(0, len(eligible) - 1, ANCHORS_PER_VECTOR)})
            anchors = pick
    for j, k in enumerate(anchors):
        for key, v in recs[k]["state"].items():
            arr[f"anchor{j}_{key}"] = np.asarray(v)
        arr[f"anchor{j}_k"] = np.array(k)
    meta = {"kind": MAG, "config": full, "unit": inp["unit"], "samples": int(len(mags)),
            "digest": FW.input_digest(mags), "checkpoints": K, "anchors": len(anchors),
            "accepted_checkpoints": int(arr["accepted"].sum()),
            "final": None if cal.accepted is None else {"hard_iron": cal.accepted.hard_iron.tolist(),
                                                        "field": float(cal.accepted.field)}}
    return arr, meta


def linear_records(name, source, cfg):
    inp = FW.vector_input(source)
    X, Y = inp["X"], inp["Y"]
    n, m = source["n"], source["m"]
    kw = {k: v for k, v in cfg.items() if k not in ("window", "estep_every")}
    recs, _ = FW.stream_records_python(X, Y, n, m, cfg["window"], cfg["estep_every"], **kw)
    K = len(recs)
    arr = {"index": np.array([r["index"] for r in recs], np.int64),
           "status": np.array([r["status"] for r in recs], np.int64),
           "theta": np.array([r["theta"] for r in recs]).reshape(K, n),
           "sigma": np.array([r["sigma"] for r in recs]).reshape(K, m),
           "d": np.array([r["d"] for r in recs]).reshape(K, m), "a": np.array([r["a"] for r in recs]).reshape(K, m),
           "cnt": np.array([r["cnt"] for r in recs]).reshape(K, -1)}
    meta = {"kind": LINEAR, "config": cfg, "samples": int(X.shape[0]), "n": n, "m": m,
            "digest": FW.input_digest(np.concatenate([X.ravel(), Y.ravel()])), "checkpoints": K}
    return arr, meta


def generate(only=None):
    index = {"generator": "tools/gen_golden.py", "feedback": "portable (mkc_stream/calib/portable.py)",
             "libm_fingerprint": libm_fingerprint(), "tolerances": FW.TOLERANCES,
             "float_segment_tolerance": 1e-4, "vectors": []}
    files = {}
    for name, kind, source, cfg, replayable in VECTORS:
        if only and name not in only:
            continue
        arr, meta = (mag_records if kind == MAG else linear_records)(name, source, cfg)
        meta.update({"name": name, "source": source, "replay": replayable, "file": f"{name}.npz"})
        index["vectors"].append(meta)
        files[name] = arr
        print(f"  {name}: {meta['samples']} samples, {meta['checkpoints']} checkpoints"
              + (f", {meta['accepted_checkpoints']} accepted, {meta['anchors']} anchors" if kind == MAG else ""))
    return index, files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="regenerate in memory and compare with the stored files")
    ap.add_argument("--only", nargs="*", help="vector names (default: all)")
    args = ap.parse_args(argv)
    index, files = generate(args.only)
    if args.check:
        stored = json.loads((OUT / "index.json").read_text())
        by_name = {v["name"]: v for v in stored["vectors"]}
        bad = 0
        for v in index["vectors"]:
            old = np.load(OUT / v["file"])
            new = files[v["name"]]
            same = set(old.files) == set(new) and all(
                np.array_equal(old[k], new[k], equal_nan=new[k].dtype.kind == "f") for k in new)
            same = same and by_name.get(v["name"], {}).get("digest") == v["digest"]
            print(f"  {v['name']}: {'current' if same else 'STALE'}")
            bad += not same
        return 1 if bad else 0
    OUT.mkdir(parents=True, exist_ok=True)
    for name, arr in files.items():
        np.savez_compressed(OUT / f"{name}.npz", **arr)
    if args.only:
        stored = json.loads((OUT / "index.json").read_text())
        keep = [v for v in stored["vectors"] if v["name"] not in args.only]
        index["vectors"] = sorted(keep + index["vectors"], key=lambda v: [x[0] for x in VECTORS].index(v["name"]))
    (OUT / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    total = sum(p.stat().st_size for p in OUT.iterdir())
    print(f"wrote {OUT.relative_to(ROOT)}: {total / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
