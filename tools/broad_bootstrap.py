#!/usr/bin/env python
"""How far apart must two calibrations of one BROAD trial be before the difference is not noise?
A moving-block bootstrap of the trial, every method refitted on each resample.

    python tools/broad_bootstrap.py                          # trial 26, 40 resamples
    python tools/broad_bootstrap.py --trial 03 --resamples 20 --methods mkc-em-geo-dir,scipy-geo-soft_l1

The trial (with the known distortion of tools/broad_truth.py) is cut into blocks of --block seconds;
a resample draws as many blocks with replacement, in time order of the draw. On each resample every
method is fitted to all the resample's samples, and the floor (least squares on the resample's
known-clean samples) to those only; the figures are |b - b_floor| in uT (b_floor of the same
resample) and the heading error against the motion capture (deg RMS, broad_truth's definition, over
the resample's heading rows). Printed per method: the full-trial figure, the bootstrap mean and
standard deviation; and, paired over the resamples, the difference of each method from the first
one (mean +- standard error, and on how many resamples the first is at most the other).

Blocks keep the trial's slow structure (rest phases, the phone's passes, the slow rotation) inside a
resample; their length (default 2 s, ~570 samples) is longer than the residual's correlation time.
A developer tool, run on demand (not a test).
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
import warnings

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from broad_truth import Case, heading_error_rms  # noqa: E402
from study_ellipsoid import discover_methods  # noqa: E402

from mkc_stream import fit_ellipsoid  # noqa: E402

DEFAULT_METHODS = "mkc-em-geo-dir,mkc-em,scipy-alg-cauchy,scipy-alg-soft_l1,scipy-alg-huber,scipy-geo-cauchy,scipy-geo-soft_l1,scipy-geo-huber,ls"


def block_resample(n_rows, block, rng):
    """Row indices of one moving-block resample: ceil(n / block) blocks of `block` rows, each
    starting at a uniformly drawn row."""
    k = -(-n_rows // block)
    starts = rng.integers(0, n_rows - block + 1, size=k)
    return (starts[:, None] + np.arange(block)[None, :]).ravel()[:n_rows]


def figures(case, methods, names, rows_idx):
    """{method: (|b - b_floor| uT, heading deg RMS)} on the rows rows_idx of case.raw_all."""
    raw_all, clean_all = case.raw_all, case.clean_all
    finite = case.finite[rows_idx]
    idx = rows_idx[finite]
    raw = raw_all[idx]
    b_floor = fit_ellipsoid(raw[clean_all[idx]], "ls").hard_iron
    # heading rows of the resample: the case's heading rows whose magnetometer row was drawn, once
    # per draw (a row drawn twice counts twice, as in the fit)
    kq, km = case.rows
    pos = {int(m): j for j, m in enumerate(km)}
    sel = np.array([pos[int(r)] for r in idx if int(r) in pos], dtype=int)
    hrows = (kq[sel], km[sel])
    out = {}
    for m in names:
        kind, runner = methods[m]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                b, S, F, _ = runner(raw)
        except Exception:  # noqa: BLE001 - a failed fit is a missing figure, counted
            out[m] = (np.nan, np.nan)
            continue
        out[m] = (float(np.linalg.norm(b - b_floor)), heading_error_rms(b, S, raw_all, case.trial, hrows))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-root", default=str(REPO.parent / "shared" / "data" / "broad"))
    ap.add_argument("--trial", default="26")
    ap.add_argument("--methods", default=DEFAULT_METHODS, help="comma list; the first is compared with the others")
    ap.add_argument("--resamples", type=int, default=40)
    ap.add_argument("--block", type=float, default=2.0, help="block length, s")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)

    case = Case(a.data_root, a.trial)
    available, _ = discover_methods()
    names = [m for m in a.methods.split(",") if m in available]
    missing = [m for m in a.methods.split(",") if m not in available]
    if missing:
        print(f"not available here, skipped: {', '.join(missing)}")
    n = len(case.raw_all)
    block = max(1, int(round(a.block * case.trial["fs"])))
    print(f"BROAD {a.trial}: {n} rows, {int(case.clean.sum())} known-clean, blocks of {block} rows "
          f"({a.block:g} s), {a.resamples} resamples")
    full = figures(case, available, names, np.arange(n))
    rng = np.random.default_rng(a.seed)
    boot = {m: [] for m in names}
    t0 = time.perf_counter()
    for i in range(a.resamples):
        f = figures(case, available, names, block_resample(n, block, rng))
        for m in names:
            boot[m].append(f[m])
        if (i + 1) % 5 == 0:
            print(f"  {i + 1}/{a.resamples} resamples, {time.perf_counter() - t0:.0f} s", flush=True)
    B = {m: np.array(v) for m, v in boot.items()}
    ref = names[0]
    print(f"\n{'method':<20}{'|b-b_floor| full':>17}{'boot mean':>11}{'boot sd':>9}"
          f"{'heading full':>14}{'boot mean':>11}{'boot sd':>9}   paired vs {ref}: |b-b_floor| diff, heading diff")
    for m in names:
        x = B[m]
        line = (f"{m:<20}{full[m][0]:17.4f}{np.nanmean(x[:, 0]):11.4f}{np.nanstd(x[:, 0], ddof=1):9.4f}"
                f"{full[m][1]:14.4f}{np.nanmean(x[:, 1]):11.4f}{np.nanstd(x[:, 1], ddof=1):9.4f}")
        if m != ref:
            d = B[ref] - x
            ok = np.isfinite(d).all(axis=1)
            d = d[ok]
            se = d.std(axis=0, ddof=1) / np.sqrt(len(d))
            line += (f"   {d[:, 0].mean():+.4f} +- {se[0]:.4f} uT ({ref} <= on {int((d[:, 0] <= 0).sum())}/{len(d)}),"
                     f" {d[:, 1].mean():+.4f} +- {se[1]:.4f} deg ({int((d[:, 1] <= 0).sum())}/{len(d)})")
        fails = int((~np.isfinite(x[:, 0])).sum())
        print(line + (f"  [{fails} failed fits]" if fails else ""))


if __name__ == "__main__":
    main()
