#!/usr/bin/env python
"""The C port (firmware_ref/) beside the Numba kernels, in one process, on the same data.

    python tools/bench_firmware.py             # W = 256, K = 32 (the issue's configuration)
    python tools/bench_firmware.py --samples 400000 --json out/bench_firmware.json

Rows (best of 3; the C side is the double build with the firmware capacities n = 9, m = 1, W = 256,
-O2, called once per run through ctypes, so the call overhead is negligible):
  learn_many   StreamingMKC.learn_many vs mkc_stream_learn_many on tools/bench_stream.py's ellipsoid
               stream (10% bursts, shuffled so every window is well-posed); also checks that both end
               with the same theta, bit for bit
  E-step       one E-step + rebuild on the full window, repeated (bench_stream.py's estep_cost)
  magcal       MagCalibrator.update vs mkc_mag_push_many on the sweep-ordered raw stream
Then the C-only benchmark binaries (firmware_ref/build/bench, bench_float) for the float build.
"""
from __future__ import annotations

import argparse
import ctypes as C
import json
import pathlib
import subprocess
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from bench_stream import ellipsoid_raw, ellipsoid_stream  # noqa: E402
from bench_stream import estep_cost as estep_numba  # noqa: E402

from mkc_stream import cport as FW  # noqa: E402
from mkc_stream.calib.streaming import MagCalibrator  # noqa: E402
from mkc_stream.stream import StreamingMKC  # noqa: E402


def best_of(fn, repeat=3):
    best = np.inf
    out = None
    for _ in range(repeat):
        t, out = fn()
        best = min(best, t)
    return best, out


def learn_many_rate(make, X, Y, W):
    def run():
        est = make()
        est.learn_many(X[:2 * W], Y[:2 * W])
        t0 = time.perf_counter()
        est.learn_many(X[2 * W:], Y[2 * W:])
        return time.perf_counter() - t0, est
    dt, est = best_of(run)
    return (X.shape[0] - 2 * W) / dt, est


def estep_c(est, repeat=200):
    dll = est.lib.dll
    dll.mkc__estep_window.argtypes = [C.c_void_p]
    dll.mkc__rebuild.argtypes = [C.c_void_p]
    dll.mkc__rebuild.restype = C.c_int
    saved = est._buf.copy()
    t0 = time.perf_counter()
    for _ in range(repeat):
        dll.mkc__estep_window(est._addr)
        dll.mkc__rebuild(est._addr)
    dt = (time.perf_counter() - t0) / repeat
    est._buf[:] = saved
    return dt


def magcal_rate(make, raw, W):
    def run():
        cal = make()
        cal.learn_many(raw[:4 * W])
        t0 = time.perf_counter()
        cal.learn_many(raw[4 * W:])
        return time.perf_counter() - t0, cal
    dt, cal = best_of(run)
    return (len(raw) - 4 * W) / dt, cal


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    W, Kk, T = 256, 32, args.samples
    FW.build("build/libmkc_bench.so", "build/bench", "build/bench_float")
    X, Y = ellipsoid_stream(T)
    raw = ellipsoid_raw(min(T, 100_000))
    res = {"W": W, "K": Kk, "samples": T}
    r_nb, e_nb = learn_many_rate(lambda: StreamingMKC(9, 1, window=W, estep_every=Kk), X, Y, W)
    r_c, e_c = learn_many_rate(lambda: FW.CStreamingMKC(9, 1, window=W, estep_every=Kk, precision="bench"), X, Y, W)
    same = bool(np.array_equal(e_nb.theta, e_c.theta))
    es_nb, es_c = estep_numba(e_nb), estep_c(e_c)
    m_nb, _ = magcal_rate(lambda: MagCalibrator(window=W, estep_every=Kk, keep_history=False), raw, W)
    m_c, _ = magcal_rate(lambda: FW.CMagCalibrator(window=W, estep_every=Kk, precision="bench", keep_history=False),
                         raw, W)
    res.update({"learn_many": {"numba": r_nb, "c_double": r_c, "theta_bitwise_equal": same},
                "estep_rebuild_s": {"numba": es_nb, "c_double": es_c},
                "magcal": {"python": m_nb, "c_double": m_c}})
    print(f"ellipsoid n = 9, m = 1, W = {W}, K = {Kk}; {T} samples; best of 3; C double build, firmware "
          f"capacities, -O2")
    print(f"  {'':26s} {'Python/Numba':>14s} {'C double':>14s} {'C / Numba':>10s}")
    print(f"  {'learn_many (samples/s)':26s} {r_nb:14,.0f} {r_c:14,.0f} {r_c / r_nb:10.2f}   "
          f"(theta bitwise equal at the end: {same})")
    print(f"  {'  per sample (us)':26s} {1e6 / r_nb:14.3f} {1e6 / r_c:14.3f}")
    print(f"  {'E-step + rebuild (us)':26s} {es_nb * 1e6:14.1f} {es_c * 1e6:14.1f} {es_nb / es_c:10.2f}")
    print(f"  {'MagCalibrator (samples/s)':26s} {m_nb:14,.0f} {m_c:14,.0f} {m_c / m_nb:10.2f}")
    print("\nC-only benchmark (firmware_ref/build/bench*, its own synthetic data):")
    res["c_only"] = {}
    for b in ("bench", "bench_float"):
        out = subprocess.run([str(FW.BUILD_DIR / b)], capture_output=True, text=True).stdout
        res["c_only"][b] = out
        print("  " + out.rstrip().replace("\n", "\n  "))
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
