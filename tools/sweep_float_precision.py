#!/usr/bin/env python
"""How closely a float build of the C port follows the double reference over many streams, not only
the golden vectors, and whether its departures cost accuracy against the truth.

    python tools/sweep_float_precision.py                       # 60 streams, all-float on the host
    python tools/sweep_float_precision.py --board an386         # the all-float build on the emulated M4F
    python tools/sweep_float_precision.py --precision float     # the default float build instead
    python tools/sweep_float_precision.py --rounded-input       # the double on inputs rounded to float
    python tools/sweep_float_precision.py --streams 120 --json out/sweep.json
    python tools/sweep_float_precision.py --harness-dir /tmp/variant/build/qemu   # programs built elsewhere

Streams: `mkc_stream.calib.synthetic.synthetic_mag` (3000 samples at 50 Hz, field 50 uT, hard iron up
to 30 uT, soft-iron spread 0.25, noise 0.3 uT) with seeds from --seed0, bursts covering 10% and 25% of
the samples in turn, replayed at the firmware capacity (W = 256, K = 32, the direction policy) through
firmware_ref/target/'s replay harness (tools/replay_harness.py). The streams are made here through
BLAS, so their last bits, and with them a stream's figures, can differ from one CPU to another; the
summary over many streams is the measure.

Per stream, the float build (host, or --board) against the double build on the host: whether every
checkpoint takes the same accept decision, the largest relative difference over the checkpoints both
accepted (theta, b / F, S, F: tools/replay_harness.py accepted_differences), the first accepted
checkpoint beyond 1e-4 and whether a cold start (the checkpoint's E-step count rising by more than one)
came at or just before it; and each build's error against the stream's truth (the median over its
accepted checkpoints of max |b - b_true| / F_true). --rounded-input replaces the float build by the
double build replaying the stream rounded to float: how far the reference itself moves when its input
moves by float's rounding.

Exit status 0 (a measurement), 2 when the harness cannot be built or run.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import replay_harness as RH  # noqa: E402
from mkc_stream import cport as FW  # noqa: E402
from mkc_stream.calib.synthetic import synthetic_mag  # noqa: E402

QEMU_DIR = ROOT / "firmware_ref" / "build" / "qemu"
BURSTS = (0.10, 0.25)
LINES = (1e-4, 1e-3)           # the departures counted (relative)


def build(board: str, precision: str) -> None:
    """The host harness (double and `precision`) and, for a board, its program."""
    targets = ["build/qemu/host_double", f"build/qemu/host_{precision}"]
    if board != "host":
        targets.append(f"build/qemu/{board}_{precision}.elf")
    proc = FW.run_make("-j2", *targets)
    if proc.returncode != 0:
        raise RH.HarnessError(f"make {' '.join(targets)} failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")


def truth_error(recs: np.ndarray, b_true: np.ndarray, field: float) -> float:
    """Median over the accepted checkpoints of max |b - b_true| / F_true (NaN if none accepted)."""
    acc = recs[:, RH.O_ACCEPTED] == 1
    if not acc.any():
        return float("nan")
    return float(np.median(np.max(np.abs(recs[acc, RH.O_HARD:RH.O_HARD + 3] - b_true), axis=1) / field))


def compare(other: np.ndarray, ref: np.ndarray) -> dict:
    """The figures of one stream: other and ref are record arrays without their final record. A build
    may take a checkpoint the other does not (a different decision): the records are paired by the
    samples seen, and the decisions count as different."""
    same_checkpoints = len(other) == len(ref) and np.array_equal(other[:, RH.O_SEEN], ref[:, RH.O_SEEN])
    if not same_checkpoints:
        _, io, ir = np.intersect1d(other[:, RH.O_SEEN], ref[:, RH.O_SEEN], return_indices=True)
        other, ref = other[io], ref[ir]
    diffs, n_acc = RH.accepted_differences(other, ref)
    worst = max(diffs.values())
    both = (other[:, RH.O_ACCEPTED] == 1) & (ref[:, RH.O_ACCEPTED] == 1)
    th = ref[:, RH.O_THETA:RH.O_THETA + 9]
    dth = np.max(np.abs(other[:, RH.O_THETA:RH.O_THETA + 9] - th), axis=1) / np.max(np.abs(th), axis=1)
    beyond = np.flatnonzero(both & (dth > LINES[0]))
    first = int(beyond[0]) if len(beyond) else -1
    steps = np.diff(ref[:, RH.O_ESTEPS], prepend=0.0)
    cold = bool(first >= 0 and np.any(steps[max(first - 1, 0):first + 1] > 1))
    return {"accepted": n_acc, "same_decisions": bool(same_checkpoints and np.array_equal(other[:, RH.O_ACCEPTED], ref[:, RH.O_ACCEPTED])),
            "worst": float(worst), **{k: float(v) for k, v in diffs.items()},
            "first_beyond_checkpoint": first, "cold_start_there": cold,
            "checkpoints_beyond": int(len(beyond))}


def run_stream(seed: int, burst: float, samples: int, workdir: pathlib.Path, board: str, precision: str,
               rounded: bool, qemu_dir: pathlib.Path = QEMU_DIR) -> dict:
    s = synthetic_mag(seed=seed, N=samples, burst_fraction=burst)
    RH.write_input(workdir / "mkc_in.bin", s.raw)
    ref = RH.run_host(qemu_dir, "double", workdir)[:-1]
    if rounded:
        RH.write_input(workdir / "mkc_in.bin", s.raw.astype(np.float32).astype(np.float64))
        other = RH.run_host(qemu_dir, "double", workdir)[:-1]
    elif board == "host":
        other = RH.run_host(qemu_dir, precision, workdir)[:-1]
    else:
        other = RH.run_board(qemu_dir, board, precision, workdir)[:-1]
    row = {"seed": seed, "burst": burst, **compare(other, ref)}
    row["truth_error_reference"] = truth_error(ref, s.hard_iron, s.field)
    row["truth_error_other"] = truth_error(other, s.hard_iron, s.field)
    return row


def summarise(rows: list[dict]) -> dict:
    worst = np.array([r["worst"] for r in rows])
    e = np.array([[r["truth_error_reference"], r["truth_error_other"]] for r in rows])
    ok = np.all(np.isfinite(e), axis=1)
    beyond = [r for r in rows if r["worst"] > LINES[0]]
    return {"streams": len(rows),
            "decisions_differ": int(sum(not r["same_decisions"] for r in rows)),
            **{f"beyond_{line:g}": int(np.sum(worst > line)) for line in LINES},
            "beyond_1e-4_after_a_cold_start": int(sum(r["cold_start_there"] for r in beyond)),
            "median_worst": float(np.median(worst)), "max_worst": float(worst.max()),
            "truth_error_reference_median": float(np.median(e[ok, 0])) if ok.any() else float("nan"),
            "truth_error_other_median": float(np.median(e[ok, 1])) if ok.any() else float("nan"),
            "truth_error_largest_increase": float(np.max(e[ok, 1] - e[ok, 0])) if ok.any() else float("nan"),
            "truth_error_largest_decrease": float(np.max(e[ok, 0] - e[ok, 1])) if ok.any() else float("nan"),
            "other_worse_by_1e-3": int(np.sum(e[ok, 1] - e[ok, 0] > LINES[1])),
            "other_better_by_1e-3": int(np.sum(e[ok, 0] - e[ok, 1] > LINES[1])),
            "compared_for_accuracy": int(ok.sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--streams", type=int, default=60, help="number of streams (seeds x the two burst shares)")
    ap.add_argument("--seed0", type=int, default=100, help="first seed")
    ap.add_argument("--samples", type=int, default=3000, help="samples per stream")
    ap.add_argument("--precision", choices=("floatonly", "float"), default="floatonly",
                    help="the float build compared (floatonly: all-float; float: double normal equations and E-step)")
    ap.add_argument("--board", choices=("host",) + tuple(RH.BOARDS), default="host",
                    help="where the float build runs (the double reference runs on the host)")
    ap.add_argument("--rounded-input", action="store_true",
                    help="compare the double build on the input rounded to float instead of a float build")
    ap.add_argument("--harness-dir", type=pathlib.Path,
                    help="use the harness programs already built in this directory (host_double, host_PRECISION, "
                         "BOARD_PRECISION.elf: e.g. a variant's build/qemu) instead of building firmware_ref's")
    ap.add_argument("--json", type=pathlib.Path, help="write every stream's figures and the summary here")
    args = ap.parse_args(argv)
    qemu_dir = args.harness_dir or QEMU_DIR
    if args.harness_dir is None:
        try:
            build(args.board, args.precision)
        except RH.HarnessError as exc:
            print(exc, file=sys.stderr)
            return 2
    what = "double, input rounded to float" if args.rounded_input else f"{args.precision} on {args.board}"
    print(f"{what} against the double on the host, {args.streams} streams of {args.samples} samples")
    print(f"{'stream':>14} {'acc':>4} {'same':>5} {'worst':>8} {'first>1e-4':>10} {'cold':>5} {'err ref':>8} {'err other':>9}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="mkc-sweep-") as tmp:
        for k in range(args.streams):
            seed, burst = args.seed0 + k // len(BURSTS), BURSTS[k % len(BURSTS)]
            try:
                r = run_stream(seed, burst, args.samples, pathlib.Path(tmp), args.board, args.precision,
                               args.rounded_input, qemu_dir)
            except RH.HarnessError as exc:
                print(exc, file=sys.stderr)
                return 2
            rows.append(r)
            print(f"{f's{seed} b{burst:.2f}':>14} {r['accepted']:4d} {str(r['same_decisions']):>5} {r['worst']:8.1e} "
                  f"{r['first_beyond_checkpoint']:10d} {str(r['cold_start_there']):>5} "
                  f"{r['truth_error_reference']:8.2e} {r['truth_error_other']:9.2e}", flush=True)
    s = summarise(rows)
    print(f"\n{s['streams']} streams: decisions differ in {s['decisions_differ']}; an accepted checkpoint beyond "
          f"1e-4 in {s['beyond_0.0001']} ({s['beyond_1e-4_after_a_cold_start']} of them at a cold start), beyond "
          f"1e-3 in {s['beyond_0.001']}; worst departure per stream: median {s['median_worst']:.1e}, max "
          f"{s['max_worst']:.1e}")
    print(f"against the truth (per stream the median |b - b_true| / F over its accepted checkpoints; median over "
          f"{s['compared_for_accuracy']} streams): reference {s['truth_error_reference_median']:.3e}, {what} "
          f"{s['truth_error_other_median']:.3e}; worse by more than 1e-3 in {s['other_worse_by_1e-3']} (at most "
          f"{s['truth_error_largest_increase']:.2g}), better by as much in {s['other_better_by_1e-3']} (at most "
          f"{s['truth_error_largest_decrease']:.2g})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"compared": what, "streams": rows, "summary": s}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
