#!/usr/bin/env python
"""Long runs of the streaming estimator: fixed memory over 10^7 samples, no drift after 10^8.

    python tools/long_run.py                          # 10^7 memory run + 10^8 drift run (~3 min)
    python tools/long_run.py --samples 2e6 --memory-samples 1e6      # quick
    python tools/long_run.py --json out/long_run.json

The stream: ellipsoid features (n = 9, m = 1) of raw = S^-1 (50 uT u) + b + 0.3 uT noise with
random directions u and 10 % of the samples in 5-40 uT bursts, generated chunk by chunk (10^5
samples) so that only the estimator's state persists. W = 256, K = 32 unless told otherwise.

Checks (each printed, and returned as a dict for tests/test_long_run.py):
  - memory: tracemalloc peak of everything the stream allocates per chunk, and the process RSS,
    sampled every 10^6 samples; the state's bytes never change;
  - after the long run, at the next E-step checkpoint: the streaming theta/sigma/d equal the batch
    kernels on the same window from the same warm start (mkc_stream.verify.batch_checkpoint),
    the add/remove accumulation A just before that checkpoint (K - 1 updates after the last rebuild)
    equals the A rebuilt from the window, nothing is NaN; and the
    distance to a fresh, fully converged batch MKC-EM on the final window (information only: the
    stream runs one capped E-step and one fixed-point round per checkpoint by design).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import resource
import sys
import time
import tracemalloc

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mkc_stream.calib.ellipsoid import design_matrix  # noqa: E402
from mkc_stream.calib.synthetic import random_soft_iron  # noqa: E402
from mkc_stream.kernels import window as K  # noqa: E402
from mkc_stream.stream import StreamingMKC  # noqa: E402
from mkc_stream.verify import accumulation_drift, batch_checkpoint, capture  # noqa: E402

CHUNK = 100_000


class FeatureSource:
    """Chunks of normalised ellipsoid features with bursts; one fixed truth for the whole run."""

    def __init__(self, seed=0, burst_fraction=0.1):
        self.rng = np.random.default_rng(seed)
        self.b = self.rng.uniform(-30, 30, 3)
        self.Sinv = np.linalg.inv(random_soft_iron(self.rng))
        self.burst_fraction = burst_fraction

    def chunk(self, T):
        rng = self.rng
        u = rng.normal(size=(T, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        raw = (50.0 * u) @ self.Sinv.T + self.b + 0.3 * rng.normal(size=(T, 3))
        # bursts: blocks of 20-60 samples with one 5-40 uT offset each
        starts = np.flatnonzero(rng.random(T) < self.burst_fraction / 40.0)
        for s in starts:
            v = rng.normal(size=3)
            raw[s:s + rng.integers(20, 61)] += v * (rng.uniform(5, 40) / np.linalg.norm(v))
        X = design_matrix((raw - self.b) / 50.0)[:, None, :]     # a fixed normalisation
        return np.ascontiguousarray(X), np.ones((T, 1))


def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def memory_run(samples, W=256, Kk=32, log=print):
    src = FeatureSource(seed=1)
    est = StreamingMKC(9, 1, window=W, estep_every=Kk)
    nbytes0 = est.nbytes()
    X, Y = src.chunk(CHUNK)
    est.learn_many(X, Y)                          # compile and warm before measuring
    tracemalloc.start()
    peaks, rss = [], []
    done = CHUNK
    while done < samples:
        del X, Y
        X, Y = src.chunk(CHUNK)
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        est.learn_many(X, Y)
        peak = tracemalloc.get_traced_memory()[1] - before
        done += CHUNK
        if done % 1_000_000 == 0:
            peaks.append(peak)
            rss.append(rss_mb())
            log(f"  memory run: {done:>11,d} samples, learn_many allocated {peak} B beyond its input "
                f"(status array {CHUNK} B), RSS {rss[-1]:.1f} MB")
    tracemalloc.stop()
    return {"samples": done, "state_bytes_start": nbytes0, "state_bytes_end": est.nbytes(),
            "learn_many_extra_bytes_max": int(max(peaks) if peaks else 0), "rss_mb": rss,
            "rss_growth_mb": float(rss[-1] - rss[0]) if len(rss) > 1 else 0.0}


def drift_run(samples, W=256, Kk=32, log=print):
    src = FeatureSource(seed=2)
    est = StreamingMKC(9, 1, window=W, estep_every=Kk)
    t0 = time.perf_counter()
    done = 0
    next_report = 10_000_000
    while done < samples:
        X, Y = src.chunk(min(CHUNK, samples - done))
        est.learn_many(X, Y)
        done += X.shape[0]
        if done >= next_report:
            log(f"  drift run: {done:>12,d} samples, {done / (time.perf_counter() - t0):,.0f} samples/s "
                f"(with data generation), status {est.snapshot().status}")
            next_report += 10_000_000
    elapsed = time.perf_counter() - t0
    # feed sample by sample up to the next checkpoint, keeping the warm start
    X, Y = src.chunk(2 * Kk)
    st = est.views()          # read-only and live: they follow the stream
    drift = 0.0
    for k in range(X.shape[0]):
        pre = capture(est)
        drift = accumulation_drift(est)      # just before the checkpoint: K - 1 add/remove updates
        est.learn_one(X[k], Y[k])
        if st["cnt"][K.C_ESTEPS] > pre["esteps"]:
            break
    th_b, s_b, d_b = batch_checkpoint(est, pre)
    theta = st["theta"]
    res = {"samples": int(st["cnt"][K.C_SEEN]), "seconds": elapsed,
           "theta_rel_diff_vs_batch": float(np.linalg.norm(theta - th_b) / np.linalg.norm(th_b)),
           "sigma_rel_diff": float(np.abs(st["sigma"] - s_b).max() / np.abs(s_b).max()),
           "d_rel_diff": float(np.abs(st["d"] - d_b).max() / np.abs(d_b).max()),
           "accumulation_drift": drift,
           "all_finite": bool(all(np.all(np.isfinite(v)) for k, v in st.items() if k != "fst")),
           "restarts": int(st["cnt"][K.C_RESTARTS]), "singular": int(st["cnt"][K.C_SINGULAR]),
           "esteps": int(st["cnt"][K.C_ESTEPS])}
    from mkc_stream import MKCRegressor

    count = int(st["cnt"][K.C_COUNT])
    fresh = MKCRegressor(max_em_iter=50).fit(st["X"][:count, 0, :].copy(), st["Y"][:count, 0].copy())
    res["theta_rel_diff_vs_converged_batch"] = float(np.linalg.norm(theta - fresh.coef_) / np.linalg.norm(fresh.coef_))
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=float, default=1e8, help="drift run length (default 1e8)")
    ap.add_argument("--memory-samples", type=float, default=1e7, help="memory run length (default 1e7)")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args(argv)
    log = lambda s: print(s, flush=True)  # noqa: E731
    mem = memory_run(int(args.memory_samples), log=log)
    log(f"memory: state {mem['state_bytes_start']} B before and {mem['state_bytes_end']} B after "
        f"{mem['samples']:,d} samples; learn_many allocates at most {mem['learn_many_extra_bytes_max']} B "
        f"per call, its {CHUNK} B status array included; peak RSS growth {mem['rss_growth_mb']:.2f} MB")
    drift = drift_run(int(args.samples), log=log)
    log(f"drift: after {drift['samples']:,d} samples ({drift['seconds']:.0f} s): theta vs batch on the final "
        f"window {drift['theta_rel_diff_vs_batch']:.2e} (sigma {drift['sigma_rel_diff']:.1e}, d {drift['d_rel_diff']:.1e}), "
        f"A drift {drift['accumulation_drift']:.1e}, all finite: {drift['all_finite']}, restarts {drift['restarts']}; "
        f"vs a fully converged batch MKC-EM {drift['theta_rel_diff_vs_converged_batch']:.1e}")
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.json).write_text(json.dumps({"memory": mem, "drift": drift}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
