#!/usr/bin/env python
"""Does the direction-organised window already hold the directions a stream has seen?

    python tools/study_seen_coverage.py                    # BROAD 03 and 26 (7 replays each) + synthetic
    python tools/study_seen_coverage.py --no-synthetic --trial 03

At every checkpoint of MagCalibrator (window 512, E-step every 32, default policy "direction"),
two coverages of the 72 equal-area direction cells (quality.direction_cells), both about the same
centre, the checkpoint's trial calibration (b, S):
  (a) window: sphere_coverage(S (m_k - b)) over the window's samples, the figure the acceptance
      predicate gates on (AcceptanceRules.min_coverage);
  (b) seen: the same over every sample fed since the start of the stream.
The samples seen are kept thinned to one per cube of VOXEL_UT (the first sample that fell in it;
a long stream at a high rate holds tens of thousands of samples, most of them near earlier ones):
a kept sample stands for samples within sqrt(3) * VOXEL_UT / 2 = 0.43 uT of it, about 0.5 deg at
50 uT, so the seen coverage can differ from the unthinned figure only by cells that the stream
touched within 0.5 deg of their edge. (b) >= (a) up to that. Reported per stream: the largest and
the median of (b - a) over the checkpoints with a trial, how many checkpoints were refused with
"coverage" among the failed checks, and how many of those the seen coverage would have passed
(b >= min_coverage), and at which sample the first checkpoint came that failed on coverage alone
while the seen coverage would pass (where a seen-coverage gate would have accepted, short of the
cold-start confirmation). Before the final normalisation the calibrator waits on a sphere fit's
coverage (MagCalibrator.MIN_SPHERE_COVERAGE, "waiting_coverage"); those checkpoints are counted
separately, with (a) and (b) about that sphere fit's centre (S = I). Beside it, (b - a) in the
window policy's own frame (the cells of m - c0 that kernels/magwindow.py choose_slot balances, no soft
iron): where that is small and (b - a) is not, the window kept its own cells and the gap comes
from the frame (c0 against b, the soft iron). And the same figures from the first acceptance on
(the median window and seen coverages, the largest and median (b - a)).

Streams: each BROAD trial (tools/broad_truth.py: the known distortion on the dataset's field)
whole, without its first 1, 10, 50 or 100 samples, and at half the rate (even / odd samples); and
the synthetic streams of tools/study_stream.py (synthetic_mag, seeds 3000 + i, 60 s at 50 Hz,
0 / 10 / 25 % bursts). Fed in 0.2 s chunks. A developer tool run on demand; it changes nothing in
the calibrator (a listener reads its state).
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from mkc_stream.calib.ellipsoid import robust_sphere_fit  # noqa: E402
from mkc_stream.calib.quality import N_BANDS, N_SECTORS, direction_cells  # noqa: E402
from mkc_stream.calib.streaming import MagCalibrator  # noqa: E402
from mkc_stream.calib.synthetic import synthetic_mag  # noqa: E402

N_CELLS = N_BANDS * N_SECTORS
CHUNK_S = 0.2
#: edge of the cubes (raw units, uT) that thin the samples seen (module doc)
VOXEL_UT = 0.5


def cells_about(raw, b, S):
    """The direction cell of every sample, calibrated as S (m - b); -1 for a zero vector."""
    v = (raw - b) @ np.asarray(S).T
    n = np.linalg.norm(v, axis=1)
    ok = n > 0
    out = np.full(len(raw), -1, dtype=np.int64)
    out[ok] = direction_cells(v[ok] / n[ok, None])
    return out


def coverage_of(cells):
    """Fraction of the 72 cells holding at least one sample (quality.sphere_coverage on cells)."""
    cells = cells[cells >= 0]
    return float(np.unique(cells).size) / N_CELLS


def replay(raw, rate_hz, window, estep_every):
    """Feed raw (T, 3) finite samples; one record per checkpoint: (kind, window cov, seen cov, refused, seen passes)."""
    cal = MagCalibrator(window=window, estep_every=estep_every, keep_history=False)
    min_cov = cal.rules.min_coverage
    records = []
    kept = np.empty_like(raw)
    state = {"fed": 0, "kept": 0, "voxels": set()}

    def thinned_seen(upto):
        """The samples raw[:upto] thinned to one per voxel (every sample fed is finite here, so
        the samples seen are a prefix of raw)."""
        for k in range(state["fed"], upto):
            key = tuple(np.floor(raw[k] / VOXEL_UT).astype(np.int64))
            if key not in state["voxels"]:
                state["voxels"].add(key)
                kept[state["kept"]] = raw[k]
                state["kept"] += 1
        state["fed"] = upto
        return kept[:state["kept"]]

    def at_checkpoint(c):
        ev = c.last_event
        seen = thinned_seen(ev.samples_seen)
        win, _ = c._window_raw()
        rej = c.last_rejection
        trial = c.trial
        if trial is not None and trial.samples_seen == ev.samples_seen:
            a = coverage_of(cells_about(win, trial.hard_iron, trial.soft_iron))
            b = coverage_of(cells_about(seen, trial.hard_iron, trial.soft_iron))
            refused = rej is not None and "coverage" in rej.failed
            only = refused and tuple(rej.failed) == ("coverage",)
            # the same two figures in the window policy's own frame (cells of m - c0, no soft iron)
            pa = coverage_of(cells_about(win, c.c0, np.eye(3)))
            pb = coverage_of(cells_about(seen, c.c0, np.eye(3)))
            records.append(("trial", a, b, refused, refused and b >= min_cov, ev.samples_seen, only, pb - pa))
        elif rej is not None and rej.code == "waiting_coverage":
            fit = robust_sphere_fit(win) if len(win) >= 8 else None
            if fit is None:
                return
            a = coverage_of(cells_about(win, fit[0], np.eye(3)))
            b = coverage_of(cells_about(seen, fit[0], np.eye(3)))
            records.append(("sphere", a, b, True, b >= c.MIN_SPHERE_COVERAGE, ev.samples_seen, False, 0.0))

    cal.add_listener(at_checkpoint)
    chunk = max(1, int(CHUNK_S * rate_hz))
    for s in range(0, len(raw), chunk):
        cal.learn_many(raw[s:s + chunk])
    return records, cal


def after_first_acceptance(trials, first):
    """Median window and seen coverage, largest and median (b - a), over the trial checkpoints from
    the first acceptance on (NaN when none was accepted)."""
    after = [r for r in trials if first is not None and r[5] >= first]
    if not after:
        nan = float("nan")
        return {"after_median_window": nan, "after_median_seen": nan, "after_largest_diff": nan,
                "after_median_diff": nan}
    a = np.array([r[1] for r in after])
    b = np.array([r[2] for r in after])
    return {"after_median_window": float(np.median(a)), "after_median_seen": float(np.median(b)),
            "after_largest_diff": float((b - a).max()), "after_median_diff": float(np.median(b - a))}


def summary(label, records, cal, log):
    tr = [r for r in records if r[0] == "trial"]
    sp = [r for r in records if r[0] == "sphere"]
    d = np.array([r[2] - r[1] for r in tr]) if tr else np.zeros(0)
    row = {"stream": label, "trial_checkpoints": len(tr),
           "largest_diff": float(d.max()) if len(d) else float("nan"),
           "median_diff": float(np.median(d)) if len(d) else float("nan"),
           "refused_coverage": sum(r[3] for r in tr), "seen_would_pass": sum(r[4] for r in tr),
           "sphere_waits": len(sp), "sphere_seen_would_pass": sum(r[4] for r in sp),
           "sphere_largest_diff": max((r[2] - r[1] for r in sp), default=float("nan")),
           **after_first_acceptance(tr, cal.first_accepted_at),
           "policy_frame_largest_diff": max((r[7] for r in tr), default=float("nan")),
           "policy_frame_median_diff": float(np.median([r[7] for r in tr])) if tr else float("nan"),
           "only_coverage_seen_passes": [r[5] for r in tr if r[4] and r[6]],
           "accepted": cal.accepted is not None,
           "first_accepted": cal.first_accepted_at}
    log(f"  {label:22s} {row['trial_checkpoints']:5d}  {row['largest_diff']:6.3f}  {row['median_diff']:6.3f}"
        f"   {row['refused_coverage']:4d} / {row['seen_would_pass']:4d}"
        f"      {row['sphere_waits']:4d} / {row['sphere_seen_would_pass']:4d}  {row['sphere_largest_diff']:6.3f}"
        f"   {'yes' if row['accepted'] else 'NO'} {row['first_accepted']}"
        f"   {len(row['only_coverage_seen_passes'])} {min(row['only_coverage_seen_passes'], default='-')}"
        f"   policy frame {row['policy_frame_largest_diff']:.3f} {row['policy_frame_median_diff']:.3f}"
        f"   after acceptance: a {row['after_median_window']:.3f} b {row['after_median_seen']:.3f} (b-a) max"
        f" {row['after_largest_diff']:.3f} median {row['after_median_diff']:.3f}")
    return row


HEADER = ("  stream                 ckpts  max(b-a) median   refused cov / seen passes   sphere waits / seen passes"
          "  max(b-a)  accepted (first at sample)  only coverage failed, seen passes (first at sample)"
          "  policy frame max / median (b-a)  after the first acceptance: median a, b; max / median (b-a)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default=str(REPO.parent / "shared" / "data" / "broad"))
    ap.add_argument("--trial", default="03,26")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--window", type=int, default=512)
    ap.add_argument("--estep-every", type=int, default=32)
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--no-real", action="store_true")
    args = ap.parse_args(argv)
    log = lambda s="": print(s, flush=True)  # noqa: E731
    log(f"coverage (fraction of {N_CELLS} cells): (a) window, (b) all samples seen; about the checkpoint's trial (b, S)")
    rows = []
    if not args.no_real:
        from broad_truth import Case
        for key in args.trial.split(","):
            c = Case(args.data_root, key)
            log(f"\nBROAD {key}: {len(c.raw)} samples at {c.trial['fs']:.1f} Hz")
            log(HEADER)
            replays = [("whole", c.raw, 1)] + [(f"drop {k}", c.raw[k:], 1) for k in (1, 10, 50, 100)] + \
                [("half even", c.raw[::2], 2), ("half odd", c.raw[1::2], 2)]
            for label, raw, step in replays:
                recs, cal = replay(np.ascontiguousarray(raw), c.trial["fs"] / step, args.window, args.estep_every)
                rows.append(summary(f"{key} {label}", recs, cal, log))
    if not args.no_synthetic:
        for frac in (0.0, 0.1, 0.25):
            log(f"\nsynthetic, bursts {frac:.0%}")
            log(HEADER)
            for i in range(args.seeds):
                syn = synthetic_mag(seed=3000 + i, N=3000, burst_fraction=frac, rate_hz=50.0)
                recs, cal = replay(syn.raw, 50.0, args.window, args.estep_every)
                rows.append(summary(f"{frac:.0%} seed {3000 + i}", recs, cal, log))
    if rows:
        big = max(rows, key=lambda r: r["largest_diff"] if np.isfinite(r["largest_diff"]) else -1)
        log(f"\nlargest (b - a) over all streams: {big['largest_diff']:.3f} ({big['stream']}); checkpoints refused "
            f"for coverage: {sum(r['refused_coverage'] for r in rows)}, of which the seen coverage would pass "
            f"{sum(r['seen_would_pass'] for r in rows)}; sphere-fit waits {sum(r['sphere_waits'] for r in rows)}, "
            f"seen would pass {sum(r['sphere_seen_would_pass'] for r in rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
