#!/usr/bin/env python
"""How closely the C port's all-float build follows the double reference, and where it departs.

    python tools/measure_float_precision.py                 # every golden magnetometer vector
    python tools/measure_float_precision.py --vectors qmc5883l_filtered --json out.json

Builds the all-float library (`-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0`, which puts
the checkpoint code in float too: no double arithmetic, for an FPU without double) at host capacity,
so that every vector's window fits, and the double library beside it, in --build-dir (default: the
system temporary directory). `--extra-cflags=-DMKC_CHECKPOINT_DOUBLE=1` measures the all-float
estimator with the checkpoint code in double instead. Then, per golden vector:

- free-running: the all-float calibrator over the vector's stored input against the vector's
  checkpoints (the Python reference, which the double build reproduces bit for bit): the same
  checkpoints and accept decisions, and at every accepted checkpoint the relative differences
  theta (max |dtheta| / max |theta|), b (max |db| / F), S (max |dS| / max |S|) and F (|dF| / F);
  the worst of each, the first accepted checkpoint beyond --tol, and the stage where the run left
  the reference before it (the first checkpoint whose sigma or d is off by more than 1e-3:
  "E-step sigma/d"; else whose theta is off by more than tol / 10: "normal-equation solve"). A
  departure the checkpoint code starts (a normalisation, a cold start from the sphere fit) shows
  there as the stage it moved first, usually the E-step: the isolated stages below tell them apart.
- stages, isolated at the vector's stored reference states (anchors): the same inputs through the
  float and the double build's normal-equation solve (mkc__spd_solve on the anchor's A, b), E-step
  (mkc__estep_channel on the anchor window's squared residuals, warm-started as the stream does),
  normaliser (mkc__log_normaliser_grad at the anchor's sigma and a / d) and robust sphere fit
  (mkc__robust_sphere_fit on the anchor's window: max |db| / F, |dF| / F); and at every reference
  trial, the calibration from theta (mkc__geometry_from_theta, raw_geometry,
  calibration_from_geometry: b / F, S, F); the largest relative difference of each. The sphere fit
  and the calibration give both builds the same inputs: the reference's values rounded to float.

Exit status 0 when every vector is within --tol with equal decisions, 1 otherwise, 2 when the
library cannot be built. The linear (non-magnetometer) vectors are not part of this measure.
"""
from __future__ import annotations

import argparse
import ctypes as C
import json
import pathlib
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import golden as GV  # noqa: E402  (tools/golden.py)

FIRMWARE_DIR = ROOT / "firmware_ref"
HOST_CAPACITY = "-DMKC_N=12 -DMKC_M=4 -DMKC_W=1024"
ALL_FLOAT = "-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0"
HOST_N = 12                      # MKC_N of the host capacity: the stride of A in mkc__spd_solve
QUANTITIES = ("theta", "b", "S", "F")
SIGMA_D_STAGE = 1e-3             # sigma or d off by more than this: the E-step left the reference


def build(build_dir: pathlib.Path, extra_cflags: str = "", with_double: bool = True) -> tuple[pathlib.Path, pathlib.Path]:
    """(all-float, double) shared libraries at host capacity, built with firmware_ref/Makefile's flags.

    The all-float one is the Makefile's float shared-object rule with the all-float flags (and
    extra_cflags, e.g. -DMKC_CHECKPOINT_DOUBLE=1) in its variant, in a build directory of its own,
    so nothing of firmware_ref/build is touched. with_double=False builds only the all-float one."""
    fo_dir, ref_dir = build_dir / "allfloat", build_dir / "double"
    flags = f"V_host_float_pic=-O2 {HOST_CAPACITY} {ALL_FLOAT} {extra_cflags} -fPIC"
    jobs = [["BUILD=" + str(fo_dir), flags, str(fo_dir / "libmkc_float.so")]]
    if with_double:
        jobs.append(["BUILD=" + str(ref_dir), str(ref_dir / "libmkc_double.so")])
    for args in jobs:
        proc = subprocess.run(["make", "-j2", "-C", str(FIRMWARE_DIR), *args], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"make {' '.join(args)} failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return fo_dir / "libmkc_float.so", ref_dir / "libmkc_double.so"


def load(all_float_so: pathlib.Path, double_so: pathlib.Path):
    """The two libraries; the all-float one registered as precision "floatonly" for cport's classes."""
    from mkc_stream.cport import bindings as B

    fo = B._Lib("float", all_float_so)
    if fo.real_bytes != 4 or fo.acc_bytes != 4 or fo.ereal_bytes != 4:
        raise RuntimeError(f"{all_float_so} is not the all-float build (real/acc/E-step bytes "
                           f"{fo.real_bytes}/{fo.acc_bytes}/{fo.ereal_bytes})")
    B._libs["floatonly"] = fo
    return fo, B._Lib("double", double_so)


def calibration_errors(rec: dict, g, k: int) -> dict:
    from mkc_stream.cport.compare import rel_diff

    F = float(g["field"][k])
    return {"theta": rel_diff(rec["theta"], g["theta"][k]),
            "b": float(np.abs(rec["hard_iron"] - g["hard_iron"][k]).max() / F),
            "S": rel_diff(np.ravel(rec["soft_iron"]), g["soft_iron"][k]),
            "F": abs(rec["field"] - F) / F}


def departure_stage(recs: list, g, upto: int, tol: float) -> dict:
    """Where the run left the reference before checkpoint `upto`: the first checkpoint of the unbroken
    run of departed checkpoints that ends there, and the stage it shows (sigma or d off by more than
    SIGMA_D_STAGE: the E-step; else theta off by more than tol / 10: the normal-equation solve; else
    only the calibration: the checkpoint code). Early ill-posed windows, where float moves theta by
    ~1e-3 without consequence, end their own runs and are not blamed."""
    from mkc_stream.cport.compare import rel_diff

    def off(j):
        r = recs[j]
        ds = abs(r["sigma"] - g["sigma"][j]) / g["sigma"][j]
        dd = abs(r["d"] - g["d"][j]) / g["d"][j]
        return ds, dd, rel_diff(r["theta"], g["theta"][j])

    def departed(j):
        ds, dd, dt = off(j)
        return max(ds, dd) > SIGMA_D_STAGE or dt > tol / 10

    j = upto
    while j > 0 and departed(j - 1):
        j -= 1
    ds, dd, dt = off(j)
    stage = ("E-step sigma/d" if max(ds, dd) > SIGMA_D_STAGE else
             "normal-equation solve" if dt > tol / 10 else "checkpoint code")
    return {"checkpoint": j, "samples_seen": int(g["samples_seen"][j]), "stage": stage,
            "sigma_rel": ds, "d_rel": dd, "theta_rel": dt}


def free_running(meta: dict, tol: float) -> dict:
    from mkc_stream.cport.compare import c_checkpoints

    inp = GV.stored_input(meta)
    cfg = meta["config"]
    recs, _ = c_checkpoints(inp["mags"], cfg["window"], cfg["estep_every"], inp["unit"], precision="floatonly",
                            policy=cfg["policy"])
    with np.load(GV.GOLDEN_DIR / meta["file"]) as z:
        g = {k: z[k] for k in z.files}
    n = len(g["samples_seen"])
    out = {"checkpoints": n, "checkpoints_float": len(recs), "accepted": int(np.sum(g["accepted"])),
           "worst": {q: 0.0 for q in QUANTITIES}, "worst_at": {q: None for q in QUANTITIES},
           "first_beyond_tol": None, "decision_mismatches": []}
    if len(recs) != n:
        out["decision_mismatches"].append(f"checkpoint count: reference {n}, all-float {len(recs)}")
    for k, r in enumerate(recs[:n]):
        if r["samples_seen"] != g["samples_seen"][k]:
            out["decision_mismatches"].append(f"checkpoint {k}: at sample {r['samples_seen']}, reference "
                                              f"{int(g['samples_seen'][k])}")
            break
        if r["accepted"] != bool(g["accepted"][k]) or r["has_trial"] != bool(g["has_trial"][k]):
            out["decision_mismatches"].append(f"checkpoint {k} (sample {r['samples_seen']}): accepted "
                                              f"{r['accepted']} / trial {r['has_trial']}, reference "
                                              f"{bool(g['accepted'][k])} / {bool(g['has_trial'][k])}")
        if not g["accepted"][k]:
            continue
        err = calibration_errors(r, g, k)
        for q in QUANTITIES:
            if err[q] > out["worst"][q]:
                out["worst"][q], out["worst_at"][q] = err[q], int(r["samples_seen"])
        if out["first_beyond_tol"] is None and max(err.values()) > tol:
            out["first_beyond_tol"] = {"checkpoint": k, "samples_seen": int(r["samples_seen"]), **err,
                                       "departure": departure_stage(recs, g, k, tol)}
    return out


# ---- stages in isolation, at the stored reference states ----

def _anchor_states(g: dict) -> list[dict]:
    states, j = [], 0
    while f"anchor{j}_k" in g:
        states.append({key[len(f"anchor{j}_"):]: g[key] for key in g if key.startswith(f"anchor{j}_")})
        j += 1
    return states


def _squared_residuals(state: dict) -> np.ndarray:
    """e^2 of the anchor window at its theta, in float (as the all-float build would hold them)."""
    f32 = np.float32
    count = int(state["cnt"][1])
    raw = state["raw"].reshape(-1, 3)[:count].astype(f32)
    c0, s0 = state["c0s0"][:3].astype(f32), f32(state["c0s0"][3])
    x, y, z = ((raw - c0) / s0).T
    X = np.stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z], axis=1)
    r = (f32(1.0) - X @ state["theta"].astype(f32)).astype(f32)
    return (r * r).astype(f32)


def _spd_solve(lib, A9: np.ndarray, b9: np.ndarray) -> np.ndarray:
    T = C.c_float if lib.acc_bytes == 4 else C.c_double
    dt = np.float32 if lib.acc_bytes == 4 else np.float64
    A = np.zeros((HOST_N, HOST_N), dt)
    A[:9, :9] = A9
    b = np.zeros(HOST_N, dt)
    b[:9] = b9
    x, L, D = np.zeros(HOST_N, dt), np.zeros((HOST_N, HOST_N), dt), np.zeros(HOST_N, dt)
    cond = T()
    f = lib.dll.mkc__spd_solve
    f.restype = C.c_int
    f.argtypes = [C.c_void_p] * 5 + [C.c_int, C.POINTER(T)]
    st = f(A.ctypes.data, b.ctypes.data, x.ctypes.data, L.ctypes.data, D.ctypes.data, 9, C.byref(cond))
    return x[:9].astype(np.float64) if st == 0 else np.full(9, np.nan)


def _estep(lib, e2: np.ndarray, state: dict) -> tuple[float, float]:
    T = C.c_float if lib.ereal_bytes == 4 else C.c_double
    arr = np.ascontiguousarray(e2, np.float32 if lib.real_bytes == 4 else np.float64)
    P = C.POINTER(T)
    f = lib.dll.mkc__estep_channel
    f.restype = C.c_int
    f.argtypes = [C.c_void_p, C.c_int] + [T] * 7 + [C.c_int, T, T, P, P, P, P, C.POINTER(C.c_int)]
    a = float(np.sqrt(np.max(e2))) * 1.5                    # a_factor * max|residual| (StreamConfig default)
    H = (T * 3)(*[float(h) for h in state["Hes"][:3]])
    s, d, F, it = T(), T(), T(), C.c_int()
    f(arr.ctypes.data, len(arr), a, float(state["sigma"][0]), float(state["d"][0]), 0.05, 1000.0, 1e-9 * a, a, 3,
      1e-7, 0.05, H, C.byref(s), C.byref(d), C.byref(F), C.byref(it))
    return s.value, d.value


def _normaliser(lib, sigma: float, A: float) -> np.ndarray:
    T = C.c_float if lib.ereal_bytes == 4 else C.c_double
    f = lib.dll.mkc__log_normaliser_grad
    f.restype = T
    f.argtypes = [T, T, C.POINTER(T), C.POINTER(T)]
    ds, dA = T(), T()
    logZ = f(sigma, A, C.byref(ds), C.byref(dA))
    return np.array([logZ, ds.value, dA.value])


def _sphere_fit(lib, state: dict, window: int) -> np.ndarray | None:
    """(b, F) of mkc__robust_sphere_fit on the anchor's window (its raw samples as floats), or None."""
    from types import SimpleNamespace

    from mkc_stream.cport.bindings import _aligned_state
    from mkc_stream.cport.compare import load_reference_state

    cfg = lib.MagConfig()
    lib.dll.mkc_mag_config_default(C.byref(cfg))
    cfg.stream.window = window
    buf, addr = _aligned_state(lib.sizeof_mag)
    if lib.dll.mkc_mag_init(addr, C.byref(cfg)) != 0:
        raise RuntimeError(f"mkc_mag_init refused window {window}")
    load_reference_state(SimpleNamespace(lib=lib, _addr=addr),
                         dict(state, raw=state["raw"].astype(np.float32).astype(np.float64)))
    count = int(state["cnt"][1])
    b, F = (lib.real * 3)(), lib.real()
    f = lib.dll.mkc__robust_sphere_fit
    f.restype = C.c_int
    f.argtypes = [C.c_void_p, C.c_int, C.c_void_p, C.c_void_p]
    if count < 8 or not f(addr, count, b, C.byref(F)):
        return None
    return np.array([*b[:], F.value])


class _Reason(C.Structure):
    _fields_ = [("code", C.c_int32), ("fails", C.c_uint32), ("v", C.c_double * 6)]


def _calibration(lib, creal, theta: np.ndarray, c0s0: np.ndarray) -> np.ndarray | None:
    """(b, S, F) from theta in the normalisation c0s0 (mkc__geometry_from_theta, raw_geometry,
    calibration_from_geometry, whose arithmetic type is creal), or None when theta is no ellipsoid."""
    real = lib.real
    th = (real * 9)(*map(float, theta))
    c0 = (real * 3)(*map(float, c0s0[:3]))
    geom, reason = (creal * 12)(), _Reason()
    dll = lib.dll
    dll.mkc__geometry_from_theta.argtypes = [C.c_void_p] * 3
    if dll.mkc__geometry_from_theta(th, geom, C.byref(reason)) != 0:
        return None
    dll.mkc__raw_geometry.argtypes = [C.c_void_p, C.c_void_p, real]
    dll.mkc__raw_geometry(geom, c0, float(c0s0[3]))
    b, S, F = (creal * 3)(), (creal * 9)(), creal()
    dll.mkc__calibration_from_geometry.argtypes = [C.c_void_p] * 4
    dll.mkc__calibration_from_geometry(geom, b, S, C.byref(F))
    return np.array([*b[:], *S[:], F.value])


def _calibration_difference(xf: np.ndarray, xd: np.ndarray) -> float:
    """max of |db| / F, max |dS| / max |S|, |dF| / F between two (b, S, F) vectors"""
    F = abs(xd[12])
    return float(max(np.max(np.abs(xf[:3] - xd[:3])) / F, np.max(np.abs(xf[3:12] - xd[3:12])) / np.max(np.abs(xd[3:12])),
                     abs(xf[12] - xd[12]) / F))


def stages(meta: dict, fo, dbl, checkpoint_double: bool = False) -> dict:
    """Largest relative float-vs-double difference of each stage over the vector's anchors (the
    calibration: over its trials). checkpoint_double: the float library's checkpoint code is double."""
    with np.load(GV.GOLDEN_DIR / meta["file"]) as z:
        g = {k: z[k] for k in z.files}
    worst = {"normal-equation solve": 0.0, "E-step sigma": 0.0, "E-step d": 0.0, "normaliser": 0.0,
             "sphere fit": 0.0, "calibration": 0.0}
    f32 = np.float32
    for k in np.flatnonzero(g["has_trial"]):
        theta, c0s0 = g["theta"][k].astype(f32), g["c0s0"][k].astype(f32)
        xf = _calibration(fo, C.c_double if checkpoint_double else C.c_float, theta, c0s0)
        xd = _calibration(dbl, C.c_double, theta, c0s0)
        if xf is not None and xd is not None:
            worst["calibration"] = max(worst["calibration"], _calibration_difference(xf, xd))
    for st in _anchor_states(g):
        sf, sd = _sphere_fit(fo, st, meta["config"]["window"]), _sphere_fit(dbl, st, meta["config"]["window"])
        if sf is not None and sd is not None:
            worst["sphere fit"] = max(worst["sphere fit"], float(np.max(np.abs(sf - sd)) / abs(sd[3])))
        A9 = st["A"].reshape(9, 9)
        A9 = np.tril(A9) + np.tril(A9, -1).T
        xf, xd = _spd_solve(fo, A9, st["b"]), _spd_solve(dbl, A9, st["b"])
        if np.all(np.isfinite(xd)) and np.max(np.abs(xd)) > 0:
            worst["normal-equation solve"] = max(worst["normal-equation solve"],
                                                 float(np.max(np.abs(xf - xd)) / np.max(np.abs(xd))))
        e2 = _squared_residuals(st)
        (sf, df), (sd, dd) = _estep(fo, e2, st), _estep(dbl, e2, st)
        worst["E-step sigma"] = max(worst["E-step sigma"], abs(sf - sd) / sd)
        worst["E-step d"] = max(worst["E-step d"], abs(df - dd) / dd)
        sigma, A = float(st["sigma"][0]), float(st["a"][0] / st["d"][0])
        nf, nd = _normaliser(fo, sigma, A), _normaliser(dbl, sigma, A)
        worst["normaliser"] = max(worst["normaliser"], float(np.max(np.abs(nf - nd) / np.maximum(np.abs(nd), 1e-30))))
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--build-dir", type=pathlib.Path,
                    default=pathlib.Path(tempfile.gettempdir()) / "mkc-float-precision")
    ap.add_argument("--vectors", nargs="*", help="golden vector names (default: every magnetometer vector)")
    ap.add_argument("--tol", type=float, default=1e-4, help="relative tolerance (default 1e-4)")
    ap.add_argument("--json", type=pathlib.Path, help="write the report as JSON here")
    ap.add_argument("--extra-cflags", default="",
                    help="more flags for the all-float build, e.g. -DMKC_CHECKPOINT_DOUBLE=1 (use a --build-dir of "
                         "its own: the objects do not record their flags)")
    args = ap.parse_args(argv)
    try:
        fo, dbl = load(*build(args.build_dir, args.extra_cflags))
    except RuntimeError as exc:
        print(f"measure_float_precision: {exc}", file=sys.stderr)
        return 2
    index = json.loads((GV.GOLDEN_DIR / "index.json").read_text())
    vectors = [v for v in index["vectors"] if v["kind"] == "mag" and (not args.vectors or v["name"] in args.vectors)]
    report, ok = {}, True
    print(f"{'vector':28s} {'acc':>4s} " + " ".join(f"{q:>8s}" for q in QUANTITIES)
          + "  decisions  first beyond tol (stage)")
    for meta in vectors:
        fr = free_running(meta, args.tol)
        fr["stages"] = stages(meta, fo, dbl, "MKC_CHECKPOINT_DOUBLE=1" in args.extra_cflags)
        report[meta["name"]] = fr
        first = fr["first_beyond_tol"]
        where = "-" if first is None else f"sample {first['samples_seen']} ({first['departure']['stage']})"
        same = "same" if not fr["decision_mismatches"] else f"{len(fr['decision_mismatches'])} differ"
        print(f"{meta['name']:28s} {fr['accepted']:4d} " + " ".join(f"{fr['worst'][q]:8.1e}" for q in QUANTITIES)
              + f"  {same:9s}  {where}")
        ok = ok and first is None and not fr["decision_mismatches"]
    print("\nstages in isolation at the stored reference states (max relative difference, float vs double):")
    for name, fr in report.items():
        print(f"  {name:28s} " + "  ".join(f"{k} {v:.1e}" for k, v in fr["stages"].items()))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
