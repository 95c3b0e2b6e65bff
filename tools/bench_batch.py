#!/usr/bin/env python
"""Batch solver benchmarks (run on demand; targets live here, never in unit tests).

    python tools/bench_batch.py [--repeat 300] [--json out/bench_batch.json]

Measures, side by side in one process after compilation:
  - one MKC-EM fit of Example 2 (N = 100, m = 2, n = 2, 3 EM rounds)   target <= 1 ms median
  - one ellipsoid MKC-EM fit of 2000 samples (10% bursts)               target <= 20 ms median
  - the normaliser and one E-step, and least squares on the same data for scale.
Reports medians and interquartile ranges; the machine is shared, so read ratios, not absolutes.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def timeit(fn, repeat):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts = np.array(ts)
    return {"median_s": float(np.median(ts)), "q25_s": float(np.quantile(ts, 0.25)), "q75_s": float(np.quantile(ts, 0.75))}


FIRST_FIT_CODE = ("import time;t=time.perf_counter();import numpy as np;from mkc_stream import MKCRegressor;"
                  "X=np.random.default_rng(0).normal(size=(100,2,2));Y=X.sum(2);MKCRegressor().fit(X,Y);"
                  "print(time.perf_counter()-t)")


def startup_times(code=FIRST_FIT_CODE, labels=("cold_first_fit_s", "cached_first_fit_s")):
    """Run `code` twice in fresh interpreters sharing an empty Numba cache: compile, then cached start."""
    import os
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in labels:
            r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
            out[label] = float(r.stdout.strip().splitlines()[-1])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=300)
    ap.add_argument("--json")
    ap.add_argument("--no-startup", action="store_true", help="skip the fresh-interpreter start-up timing")
    args = ap.parse_args(argv)

    from mkc_stream import MKCRegressor, WLSRegressor, fit_ellipsoid
    from mkc_stream.calib.synthetic import synthetic_mag
    from mkc_stream.kernels.estep import estep_channel
    from mkc_stream.kernels.normaliser import log_normaliser_grad
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    from reproduce_paper import example2

    rng = np.random.default_rng(1)
    X, Y, _ = example2(rng, 4)
    s = synthetic_mag(seed=5, N=2000, burst_fraction=0.1)
    e = Y[:, 0] - X[:, 0] @ np.ones(2)
    a = 1.5 * np.abs(e).max()
    # warm-up (compilation)
    MKCRegressor(sigma=20, d=[1, 2], max_em_iter=3).fit(X, Y)
    fit_ellipsoid(s.raw, "mkc-em")
    fit_ellipsoid(s.raw, "ls")
    estep_channel(e, e.size, a, 20.0, 1.0, 0.05, 1e3, 1e-6 * a, a, 100, 1e-9, 0.0, np.zeros(3))

    res = {}
    res["example2_mkc_em_3_rounds"] = timeit(lambda: MKCRegressor(sigma=20, d=[1, 2], max_em_iter=3, em_tol=0.0).fit(X, Y), args.repeat)
    res["example2_mkc_em_converged"] = timeit(lambda: MKCRegressor(sigma=20, d=[1, 2]).fit(X, Y), args.repeat)
    res["example2_wls"] = timeit(lambda: WLSRegressor(d=[1, 2]).fit(X, Y), args.repeat)
    res["ellipsoid_2000_mkc_em"] = timeit(lambda: fit_ellipsoid(s.raw, "mkc-em"), max(20, args.repeat // 10))
    res["ellipsoid_2000_ls"] = timeit(lambda: fit_ellipsoid(s.raw, "ls"), max(20, args.repeat // 10))
    res["estep_one_channel_N100_cold_start"] = timeit(
        lambda: estep_channel(e, e.size, a, 20.0, 1.0, 0.05, 1e3, 1e-6 * a, a, 100, 1e-9, 0.0, np.zeros(3)), args.repeat)
    res["normaliser_call"] = timeit(lambda: [log_normaliser_grad(2.3, 40.0) for _ in range(100)], args.repeat)
    res["normaliser_call"] = {k: v / 100 for k, v in res["normaliser_call"].items()}
    if not args.no_startup:
        res["startup"] = startup_times()

    def ms(k):
        return res[k]["median_s"] * 1e3

    print("batch benchmarks (median, IQR)")
    for k, v in res.items():
        if k == "startup":
            print(f"  {'first fit, fresh interpreter, no cache':44s} {v['cold_first_fit_s']:8.2f} s (compile)")
            print(f"  {'first fit, fresh interpreter, cached':44s} {v['cached_first_fit_s']:8.2f} s")
            continue
        print(f"  {k:44s} {v['median_s'] * 1e3:10.4f} ms   [{v['q25_s'] * 1e3:.4f}, {v['q75_s'] * 1e3:.4f}]")
    print(f"\n  Example 2 MKC-EM (3 rounds): {ms('example2_mkc_em_3_rounds'):.3f} ms (target <= 1 ms; paper ~20 ms in MATLAB); "
          f"{ms('example2_mkc_em_3_rounds') / ms('example2_wls'):.0f}x WLS")
    print(f"  ellipsoid MKC-EM, 2000 samples: {ms('ellipsoid_2000_mkc_em'):.2f} ms (target <= 20 ms); "
          f"{ms('ellipsoid_2000_mkc_em') / ms('ellipsoid_2000_ls'):.1f}x least squares")
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
