#!/usr/bin/env python
"""Golden vectors for the C port (firmware_ref/): the Python reference's state at every checkpoint.

    python tools/gen_golden.py                 # (re)write tests/data/golden/
    python tools/gen_golden.py --check         # regenerate in memory, compare with the stored files
    python tools/gen_golden.py --new-inputs    # also make the inputs anew (changes every vector)

Each vector is an input (a synthetic stream from its seed, a bundled real recording, or a
multi-channel linear stream) and a configuration. The input is stored in inputs/<name>.npz as
little-endian float64 (input_mags/input_t or input_X/input_Y) with its SHA-256 in the index: tests
read it back and never rebuild it, because a synthetic stream made through BLAS (matrix products,
random rotations) differs in its last bits from one CPU to another. A new vector's input is made
here, once, from its definition (kept in the index as "source"); a regeneration keeps the stored
inputs unless --new-inputs is given.

For the magnetometer vectors MagCalibrator's feedback path (sphere fit, eigen-decompositions) is
bit-reproducible (mkc_stream/calib/portable.py, the C port's algorithms; firmware_ref/README.md
"Why portable feedback"); every checkpoint's samples seen, E-steps, status, theta, sigma, d, a, normalisation (c0, s0), decision, reason and trial
calibration (b, S, F, quality) are stored, plus "anchors": the whole reference state at a few
checkpoints, from which tests/test_firmware.py restarts the float build (teacher forcing). For the
linear vectors StreamingMKC runs and each checkpoint's index, status, theta, sigma, d, a and
counters are stored.

Files: tests/data/golden/index.json (vectors, configurations, input checksums, tolerances, a libm
fingerprint), one <name>.npz per vector (checkpoints) and one inputs/<name>.npz (its input, written
only when new, so that a regeneration leaves the inputs' bytes alone). Regenerate after any change of the Python reference
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
sys.path.insert(0, str(ROOT / "tools"))

import golden  # noqa: E402
from mkc_stream import cport as FW  # noqa: E402

OUT = golden.GOLDEN_DIR

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
    # a wrong mode that passed the gates under heavy bursts, then a pool that no longer fits the window
    # (streaming.py _pool_fits) gives way to the better trial
    ("syn_s4009_b25_pool_refit", MAG, {"kind": "synthetic", "seed": 4009, "N": 3000, "burst": 0.25}, {}, True),
    # heavy bursts with wrong modes: the cold start keeps the likelier of its two starts (WLS wins 5 of
    # its 15 here), and a pool that a strongly supported trial fits 55 times better gives way at once
    # (streaming.py _better_cold_start, confidence.residual_ratio)
    ("syn_s3299_b25_wrong_mode", MAG, {"kind": "synthetic", "seed": 3299, "N": 3000, "burst": 0.25}, {}, True),
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

def linear_stream(seed, T=1500, n=4, m=2, outlier=0.15):
    """A multi-channel linear stream y = X theta + noise with uniform outliers."""
    rng = np.random.default_rng(seed)
    scales = np.array([1.0, 3.0, 0.3, 1.0, 2.0, 0.5, 1.5, 0.7])[:n]
    X = rng.normal(size=(T, m, n)) * scales
    theta = rng.normal(size=n)
    Y = np.einsum("kmn,n->km", X, theta) + rng.normal(size=(T, m)) * (0.1 * np.arange(1, m + 1))
    bad = rng.random((T, m)) < outlier
    Y[bad] += rng.uniform(-20, 20, bad.sum())
    return X, Y


def make_input(source: dict) -> dict:
    """A new vector's input from its definition (only when (re)generating: see the module docstring).

    Magnetometer sources give {"mags" (T, 3), "t" (T,), "unit"}; "linear" gives {"X", "Y"}.
    """
    from mkc_stream.io import recording as R

    kind = source["kind"]
    if kind == "synthetic":
        from mkc_stream.calib.synthetic import synthetic_mag

        s = synthetic_mag(seed=source["seed"], N=source["N"], burst_fraction=source["burst"],
                          spike_fraction=source.get("spikes", 0.0), spike_magnitude=source.get("spike_uT", 1000.0))
        mags = s.raw.copy()
        for col, every, offset in source.get("nan", []):
            mags[offset::every, col] = np.nan
        return {"mags": mags, "t": np.asarray(s.t, np.float64), "unit": "uT"}
    if kind == "linear":
        X, Y = linear_stream(source["seed"], source["T"], source["n"], source["m"], source.get("outlier", 0.15))
        return {"X": X, "Y": Y}
    path = ROOT / source["path"]
    loaders = {"qmc5883l": R.load_qmc5883l_csv, "ck_explorer": R.load_ck_explorer_csv, "broad": R.load_broad,
               "cave_survey": R.load_cave_survey_json, "recording": R.read_recording}
    rec = loaders[kind](path)
    mags, t = rec.mag, rec.t
    cycles = int(source.get("cycles", 1))
    if cycles > 1:         # a short fixture replayed several times (a device re-shot)
        mags = np.concatenate([mags] * cycles)
        t = np.arange(len(mags), dtype=np.float64)
    return {"mags": np.ascontiguousarray(mags, np.float64), "t": np.ascontiguousarray(t, np.float64),
            "unit": rec.mag_unit}


def vector_input(name, source, stored):
    """The vector's input: the stored one when the vector exists (a regeneration keeps its input),
    else a new one made from its definition."""
    if name in stored:
        return golden.stored_input(stored[name])
    return make_input(source)


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


def mag_records(name, source, cfg, inp):
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
    arr["input_mags"] = np.ascontiguousarray(mags, "<f8")
    arr["input_t"] = np.ascontiguousarray(inp["t"], "<f8")
    meta = {"kind": MAG, "config": full, "unit": inp["unit"], "samples": int(len(mags)),
            "input_sha256": golden.input_sha256([arr["input_mags"], arr["input_t"]]), "checkpoints": K, "anchors": len(anchors),
            "accepted_checkpoints": int(arr["accepted"].sum()),
            "final": None if cal.accepted is None else {"hard_iron": cal.accepted.hard_iron.tolist(),
                                                        "field": float(cal.accepted.field)}}
    return arr, meta


def linear_records(name, source, cfg, inp):
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
           "cnt": np.array([r["cnt"] for r in recs]).reshape(K, -1),
           "input_X": np.ascontiguousarray(X, "<f8"), "input_Y": np.ascontiguousarray(Y, "<f8")}
    meta = {"kind": LINEAR, "config": cfg, "samples": int(X.shape[0]), "n": n, "m": m,
            "input_sha256": golden.input_sha256([arr["input_X"], arr["input_Y"]]), "checkpoints": K}
    return arr, meta


#: Checkpoint arrays that pass through BLAS/LAPACK or SIMD-dispatched numpy reductions: the quality
#: figures (np.mean, np.std, np.linalg.norm, whose summation order numpy picks per CPU) and the
#: condition number (a BLAS product and an SVD). Their last bits depend on the CPU, so a regeneration
#: is compared with them to a relative tolerance (measured across OpenBLAS's Haswell, Sandybridge and
#: Prescott kernels: 1.7e-15 and 3.2e-13); every other array is computed by plain loops in a fixed order
#: (calib/portable.py, the Numba kernels without fastmath) and must match bit for bit.
CPU_DEPENDENT = {"quality": 1e-12, "condition": 1e-9}


def same_checkpoints(old, new: dict) -> list:
    """The keys whose arrays differ: bit for bit, or beyond CPU_DEPENDENT's relative tolerance."""
    bad = sorted(set(old) ^ set(new))
    for k in set(old) & set(new):
        a, b = old[k], new[k]
        if k in CPU_DEPENDENT:
            if a.shape != b.shape or not np.allclose(a, b, rtol=CPU_DEPENDENT[k], atol=0.0, equal_nan=True):
                bad.append(k)
        elif not np.array_equal(a, b, equal_nan=b.dtype.kind == "f"):
            bad.append(k)
    return sorted(bad)


def checkpoints_only(arr: dict) -> dict:
    """The arrays of a vector's checkpoint file (its input goes to inputs/<name>.npz)."""
    return {k: a for k, a in arr.items() if not k.startswith("input_")}


def stored_vectors() -> dict:
    path = OUT / "index.json"
    if not path.exists():
        return {}
    return {v["name"]: v for v in json.loads(path.read_text())["vectors"] if "input_sha256" in v}


def generate(only=None, new_inputs=False):
    """The vectors' checkpoints from their inputs: the stored inputs, or (new_inputs, or a vector not
    yet stored) inputs made now from their definitions."""
    stored = {} if new_inputs else stored_vectors()
    index = {"generator": "tools/gen_golden.py", "feedback": "portable (mkc_stream/calib/portable.py)",
             "libm_fingerprint": libm_fingerprint(), "tolerances": FW.TOLERANCES,
             "float_segment_tolerance": 1e-4, "vectors": []}
    files = {}
    for name, kind, source, cfg, replayable in VECTORS:
        if only and name not in only:
            continue
        inp = vector_input(name, source, stored)
        arr, meta = (mag_records if kind == MAG else linear_records)(name, source, cfg, inp)
        meta.update({"name": name, "source": source, "replay": replayable, "file": f"{name}.npz",
                     "input_file": f"inputs/{name}.npz"})
        index["vectors"].append(meta)
        files[name] = arr
        print(f"  {name}: {meta['samples']} samples, {meta['checkpoints']} checkpoints"
              + (f", {meta['accepted_checkpoints']} accepted, {meta['anchors']} anchors" if kind == MAG else ""))
    return index, files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="regenerate in memory and compare with the stored files")
    ap.add_argument("--only", nargs="*", help="vector names (default: all)")
    ap.add_argument("--new-inputs", action="store_true",
                    help="make the inputs anew from their definitions (default: keep the stored inputs)")
    args = ap.parse_args(argv)
    index, files = generate(args.only, new_inputs=args.new_inputs)
    if args.check:
        stored = json.loads((OUT / "index.json").read_text())
        by_name = {v["name"]: v for v in stored["vectors"]}
        bad = 0
        for v in index["vectors"]:
            new = checkpoints_only(files[v["name"]])
            with np.load(OUT / v["file"]) as old:
                differ = same_checkpoints(old, new)
            if by_name.get(v["name"], {}).get("input_sha256") != v["input_sha256"]:
                differ.append("input")
            same = not differ
            print(f"  {v['name']}: {'current' if same else 'STALE (' + ', '.join(differ) + ')'}")
            bad += not same
        return 1 if bad else 0
    (OUT / "inputs").mkdir(parents=True, exist_ok=True)
    stored = stored_vectors()
    for v in index["vectors"]:
        arr = files[v["name"]]
        np.savez_compressed(OUT / v["file"], **checkpoints_only(arr))
        if stored.get(v["name"], {}).get("input_sha256") != v["input_sha256"]:
            np.savez_compressed(OUT / v["input_file"], **{k: a for k, a in arr.items() if k.startswith("input_")})
    if args.only:
        stored = json.loads((OUT / "index.json").read_text())
        keep = [v for v in stored["vectors"] if v["name"] not in args.only]
        index["vectors"] = sorted(keep + index["vectors"], key=lambda v: [x[0] for x in VECTORS].index(v["name"]))
    (OUT / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    total = sum(p.stat().st_size for p in OUT.rglob("*") if p.is_file())
    print(f"wrote {OUT.relative_to(ROOT)}: {total / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
