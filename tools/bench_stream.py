#!/usr/bin/env python
"""Streaming benchmarks (run on demand; targets live here, not in unit tests).

    python tools/bench_stream.py                 # full grid
    python tools/bench_stream.py --quick         # W = 256, K = 32 only
    python tools/bench_stream.py --json out/bench_stream.json

Measures, side by side in one process after compilation:
  - learn_many throughput, ellipsoid (n = 9, m = 1) and multi-channel (n = 6, m = 3),
    for W in {128, 256, 512, 1024} and K in {16, 32, 64}
  - learn_one latency from Python (one call per sample)
  - the state's memory per configuration (float64; the float build halves the float fields)
  - the cost of one E-step + rebuild on a full window, in isolation
  - compile time (fresh interpreter, empty cache) and cached start-up time
  - the ratio against re-solving the batch problem (MKC-EM on the window) at every sample
Targets: >= 1e6 samples/s for the ellipsoid at W = 256, K = 32; learn_one <= 5 us.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

from mkc_stream import MKCRegressor  # noqa: E402
from mkc_stream.calib.ellipsoid import design_matrix, normalisation_for  # noqa: E402
from mkc_stream.calib.synthetic import synthetic_mag  # noqa: E402
from mkc_stream.kernels import window as K  # noqa: E402
from mkc_stream.state import state_nbytes  # noqa: E402
from mkc_stream.stream import StreamingMKC  # noqa: E402


def ellipsoid_raw(T, seed=0):
    """A synthetic magnetometer stream (10 % bursts) that sweeps the sphere every 2000 samples."""
    reps = -(-T // 2000)
    return np.concatenate([synthetic_mag(seed=seed + r, N=2000, burst_fraction=0.1).raw for r in range(reps)])[:T]


def ellipsoid_stream(T, seed=0):
    """Ellipsoid features of that stream in shuffled order, so that every W-sample window covers the
    sphere: the well-posed case a plain ring buffer is for. (In sweep order a 256-sample FIFO window
    holds one patch of the sphere, where the 9-parameter ellipsoid is singular; that is the case
    MagCalibrator's direction-organised window handles, benchmarked separately below.)"""
    raw = ellipsoid_raw(T, seed)
    raw = raw[np.random.default_rng(seed).permutation(T)]
    norm = normalisation_for(raw[:2000])
    X = design_matrix(norm.apply(raw))[:, None, :]
    return np.ascontiguousarray(X), np.ones((T, 1))


def magcal_throughput(raw, W, Kk, repeat=3):
    """MagCalibrator.update on the sweep-ordered raw stream in one call (kernel + checkpoint logic)."""
    from mkc_stream.calib.streaming import MagCalibrator

    best = np.inf
    for _ in range(repeat):
        cal = MagCalibrator(window=W, estep_every=Kk, keep_history=False)
        cal.learn_many(raw[:4 * W])
        t0 = time.perf_counter()
        cal.learn_many(raw[4 * W:])
        best = min(best, time.perf_counter() - t0)
    return (len(raw) - 4 * W) / best, cal


def multichannel_stream(T, n=6, m=3, seed=1):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(T, m, n))
    Y = np.einsum("kmn,n->km", X, rng.normal(size=n)) + 0.1 * rng.normal(size=(T, m))
    bad = rng.random((T, m)) < 0.1
    Y[bad] += rng.uniform(-20, 20, bad.sum())
    return X, Y


def throughput(X, Y, W, Kk, repeat=3):
    n, m = X.shape[2], X.shape[1]
    best = np.inf
    for _ in range(repeat):
        est = StreamingMKC(n, m, window=W, estep_every=Kk)
        est.learn_many(X[:2 * W], Y[:2 * W])                 # warm the window (and the JIT)
        t0 = time.perf_counter()
        est.learn_many(X[2 * W:], Y[2 * W:])
        best = min(best, time.perf_counter() - t0)
    return (X.shape[0] - 2 * W) / best, est


def learn_one_latency(X, Y, W=256, Kk=32, calls=20000):
    n, m = X.shape[2], X.shape[1]
    est = StreamingMKC(n, m, window=W, estep_every=Kk)
    est.learn_many(X[:2 * W], Y[:2 * W])
    est.learn_one(X[0], Y[0])
    xs = [np.ascontiguousarray(X[k]) for k in range(calls)]
    ys = [np.ascontiguousarray(Y[k]) for k in range(calls)]
    t0 = time.perf_counter()
    for k in range(calls):
        est.learn_one(xs[k], ys[k])
    return (time.perf_counter() - t0) / calls


def estep_cost(est, repeat=200):
    st = est.kernel_state     # the live arrays: the kernels run on them
    e_args = [st[k] for k in ("icfg", "fcfg", "X", "Y", "theta", "sigma", "d", "a", "Hes", "R", "ebuf", "cnt", "fst")]
    r_args = [st[k] for k in ("icfg", "fcfg", "X", "Y", "C", "A", "b", "theta", "sigma", "d", "L", "D", "xs", "tprev",
                              "cnt", "fst")]
    saved = est.state
    t0 = time.perf_counter()
    for _ in range(repeat):
        K.estep_window(*e_args)
        K.rebuild(*r_args)
    dt = (time.perf_counter() - t0) / repeat
    est.load_state(saved)
    return dt


def batch_per_sample(X, Y, W, samples=200):
    """Cost of re-solving MKC-EM on the window at every sample (what streaming avoids)."""
    t0 = time.perf_counter()
    for k in range(samples):
        MKCRegressor(max_em_iter=3).fit(X[k:k + W], Y[k:k + W])
    return (time.perf_counter() - t0) / samples


def startup():
    from bench_batch import startup_times

    code = ("import time;t=time.perf_counter();import numpy as np;from mkc_stream.stream import StreamingMKC;"
            "e=StreamingMKC(9,1,256,32);r=np.random.default_rng(0);X=r.normal(size=(600,1,9));"
            "e.learn_many(X,X.sum(2));print(time.perf_counter()-t)")
    return startup_times(code, ("compile_s", "cached_start_s"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    Ws = [256] if args.quick else [128, 256, 512, 1024]
    Ks = [32] if args.quick else [16, 32, 64]
    T = args.samples
    Xe, Ye = ellipsoid_stream(T)
    Xm, Ym = multichannel_stream(T)
    res = {"throughput": [], "memory": []}
    print("learn_many throughput (samples/s), best of 3")
    print(f"  {'case':14s} {'W':>5s} {'K':>4s} {'samples/s':>12s}  {'E-step+rebuild':>15s}  (health)")
    for name, X, Y in (("ellipsoid", Xe, Ye), ("3ch x 6par", Xm, Ym)):
        for W in Ws:
            for Kk in Ks:
                rate, est = throughput(X, Y, W, Kk)
                es = estep_cost(est)
                res["throughput"].append({"case": name, "W": W, "K": Kk, "samples_per_s": rate, "estep_rebuild_s": es})
                cnt = est.state["cnt"]
                health = {"restarts": int(cnt[K.C_RESTARTS]), "singular": int(cnt[K.C_SINGULAR]),
                          "factorisations_per_sample": float(cnt[K.C_FACTORS] / cnt[K.C_SEEN])}
                res["throughput"][-1].update(health)
                print(f"  {name:14s} {W:5d} {Kk:4d} {rate:12,.0f}  {es * 1e6:12.1f} us   "
                      f"(restarts {health['restarts']}, singular {health['singular']}, "
                      f"Cholesky per sample {health['factorisations_per_sample']:.3f})")
    raw = ellipsoid_raw(T)
    print("\nMagCalibrator.update (direction-organised window, sweep order, one call)")
    res["magcal"] = []
    for W in Ws:
        rate, cal = magcal_throughput(raw, W, 32)
        res["magcal"].append({"W": W, "K": 32, "samples_per_s": rate, "accepted": cal.accepted is not None})
        print(f"  {'magcal':14s} {W:5d} {32:4d} {rate:12,.0f}   accepted: {cal.accepted is not None}")
    lat = learn_one_latency(Xe, Ye)
    res["learn_one_us"] = lat * 1e6
    print(f"\nlearn_one from Python (ellipsoid, W = 256, K = 32): {lat * 1e6:.2f} us per call (target <= 5 us)")
    for W in (128, 256, 512, 1024):
        for n, m in ((9, 1), (6, 3)):
            res["memory"].append({"n": n, "m": m, "W": W, "bytes_double": state_nbytes(n, m, W, 8),
                                  "bytes_float": state_nbytes(n, m, W, 4)})
    print("\nstate memory (bytes): " + ", ".join(f"n={r['n']} m={r['m']} W={r['W']}: {r['bytes_double']} (f64) / "
                                               f"{r['bytes_float']} (f32)" for r in res["memory"] if r["W"] in (256, 1024)))
    bp = batch_per_sample(Xe, Ye, 256)
    r256 = next(r for r in res["throughput"] if r["case"] == "ellipsoid" and r["W"] == 256 and r["K"] == 32)
    res["batch_resolve_per_sample_s"] = bp
    print(f"\nre-solving batch MKC-EM on the window every sample: {bp * 1e3:.2f} ms/sample = {1 / bp:,.0f} samples/s; "
          f"streaming is {r256['samples_per_s'] * bp:,.0f}x faster (W = 256, K = 32)")
    if not args.quick:
        res["startup"] = startup()
        print(f"start-up: compile {res['startup']['compile_s']:.1f} s (fresh cache), cached {res['startup']['cached_start_s']:.2f} s")
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
