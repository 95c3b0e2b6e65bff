#!/usr/bin/env python
"""Ground truth for magnetometer calibration on BROAD trials: a known distortion on
top of the dataset's calibrated imu_mag, hard-iron error and a heading error against the optical
motion capture.

    python tools/broad_truth.py                    # trials 03 and 26: one line per method
    python tools/broad_truth.py --trial 03 --methods ls,mkc-em,mkc-em-geo

Used by tools/study_ellipsoid.py (its --truth part); a developer tool, not a test. Reads the full
trials under <repo>/../shared/data/broad (h5py for .hdf5, scipy.io.loadmat for .mat).

Distortion. imu_mag is already calibrated (uT); raw = S_true^-1 m + b_true with b_true = (12, -30, 8)
uT and S_true = random_soft_iron(seed 20261121) (symmetric, det 1, eigenvalues within e^+-0.25), as
in tools/study_ellipsoid.py and tools/study_stream.py. (b_true, S_true) maps raw back to imu_mag
exactly, so |b - b_true| is the hard-iron error against the DATASET's calibration. That calibration
is not perfect: fitted to the movement phase, every method finds a residual hard iron in imu_mag,
about 1.9 uT in trial 03 and 3.7 uT in trial 26 (there mostly the phone's own static field: it sits
by the sensor the whole trial), and removing it lowers the heading error against the motion capture
(4.7 -> 3.7 deg, 6.1 -> 4.5 deg), so it is real. |b - b_true| therefore carries a common offset
S_true^-1 b0 for every method; differences between methods are read from |b - b_clean| (the distance
to least squares on the known-clean samples, the floor) and from the heading error.

Known-clean samples. Trial 03 (undisturbed): all samples. Trial 26 (vibrating phone): the dataset
marks no disturbance, only its movement phase; clean = movement phase AND |r_k - median(r)| <= 3.5 x
1.4826 MAD(r), r_k = |m_cal,k| - F the field-strength residual of a least-squares ellipsoid fitted
to the movement phase (quality.outlier_mask), refitted once on the kept samples and the mask
recomputed. The 45 s rest phases at the start and end are left out of it: they sit at one
orientation, and their field reads ~0.6 uT below what the movement phase's ellipsoid predicts there
(both trials), so they are not clean for a calibration.

Heading error (deg RMS). For sample k with a finite opt_quat q_k (sensor -> ENU, BROAD's [w x y z]),
in the movement phase and (trial 26) known-clean: the calibrated field S (raw_{k+L} - b) is turned
into the ENU frame by q_k, and its heading psi_k = atan2(E, N) of the horizontal part is the
direction of the horizontal field the method reports. With a perfect calibration and no disturbance
psi_k is one constant, the true horizontal field direction (magnetic north in the motion-capture
frame); the error is wrap(psi_k - psi_bar), psi_bar the circular mean of psi_k (the one unknown
constant, the angle between the motion-capture frame's north and magnetic north, is not the
calibration's to know), and the figure is the RMS over the samples. L = 3 samples (10.5 ms): the
magnetometer lags the gyroscope by 9.6-9.9 ms on BROAD (diagnose/gyro_timing), and pairing the
quaternion with the magnetometer sample 3 later lowers every method's figure by ~1 deg the same
way. The floor left (~3.2 deg for the best fits) is the motion capture's alignment, the room's field
gradient and the sensor's own non-ellipsoidal errors, which no calibration removes.

Synthetic heading error (deg RMS): a level compass swing (360 headings, 50 uT field at 60 deg
inclination) through the true distortion and back through the fitted calibration; the RMS of the
heading error atan2(-y, x) over the swing (the max of which is tools/study_stream.py's figure).
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

from mkc_stream.calib.quality import outlier_mask  # noqa: E402
from mkc_stream.calib.synthetic import random_soft_iron  # noqa: E402

BROAD_SEED = 20261121
BROAD_B_TRUE = np.array([12.0, -30.0, 8.0])
TRIALS = {"03": "03_undisturbed_slow_rotation_C.hdf5", "26": "26_disturbed_phone_vibration_A.mat"}
#: magnetometer lag behind the quaternion, in samples at 285.7 Hz (module doc)
MAG_LAG = 3
INCLINATION_DEG = 60.0


def load_trial(path):
    """dict of mag (N,3), quat (N,4) [w x y z], movement (N,) bool, fs; rows kept as stored."""
    path = pathlib.Path(path)
    if path.suffix.lower() in (".hdf5", ".h5"):
        import h5py

        with h5py.File(path, "r") as f:
            d = {k: np.asarray(f[k][()]) for k in ("imu_mag", "opt_quat", "movement")}
            fs = float(f.attrs["sampling_rate"])
    else:
        import scipy.io

        d = scipy.io.loadmat(path, variable_names=["imu_mag", "opt_quat", "movement", "sampling_rate"])
        fs = float(np.ravel(d["sampling_rate"])[0])
    return {"mag": np.asarray(d["imu_mag"], dtype=np.float64), "quat": np.asarray(d["opt_quat"], dtype=np.float64),
            "movement": np.asarray(d["movement"]).reshape(-1) > 0, "fs": fs, "name": path.stem}


def distortion():
    return BROAD_B_TRUE.copy(), random_soft_iron(np.random.default_rng(BROAD_SEED), 0.25)


def distort(mag, b_true, S_true):
    return mag @ np.linalg.inv(S_true).T + b_true


def clean_mask(trial, undisturbed):
    """Known-clean samples (module doc), over all rows (False where imu_mag is not finite)."""
    from mkc_stream import fit_ellipsoid

    ok = np.isfinite(trial["mag"]).all(axis=1)
    if undisturbed:
        return ok
    m = trial["mag"]
    sel = ok & trial["movement"]
    for _ in range(2):
        f = fit_ellipsoid(m[sel], "ls")
        r = np.full(len(m), np.nan)
        r[ok] = np.linalg.norm(f.apply(m[ok]), axis=1) - f.field
        mv = ok & trial["movement"]
        keep = np.zeros(len(m), dtype=bool)
        keep[mv] = ~outlier_mask(r[mv])
        sel = keep
    return sel


def quat_matrices(q):
    """Rotation matrices (N,3,3) sensor -> ENU from [w x y z] quaternions."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def heading_rows(trial, mask):
    """(quat row indices k, magnetometer row indices k + MAG_LAG) used by the heading error."""
    n = len(trial["mag"])
    k = np.arange(n - MAG_LAG)
    good = (np.isfinite(trial["quat"][k]).all(axis=1) & trial["movement"][k] & mask[k + MAG_LAG]
            & np.isfinite(trial["mag"][k + MAG_LAG]).all(axis=1))
    k = k[good]
    return k, k + MAG_LAG


def heading_error_rms(b, S, raw, trial, rows, return_mean=False):
    """RMS heading error (deg) of calibration (b, S) over the given rows (module doc)."""
    kq, km = rows
    R = quat_matrices(trial["quat"][kq])
    m_cal = (raw[km] - b) @ np.asarray(S).T
    e = np.einsum("kij,kj->ki", R, m_cal)
    psi = np.arctan2(e[:, 0], e[:, 1])
    mean = np.angle(np.mean(np.exp(1j * psi)))
    err = np.degrees(np.angle(np.exp(1j * (psi - mean))))
    rms = float(np.sqrt(np.mean(err * err)))
    return (rms, float(np.degrees(mean))) if return_mean else rms


def swing_heading_rms(b, S, b_true, S_true, field=50.0, inclination_deg=INCLINATION_DEG, steps=360):
    """RMS heading error (deg) over a level compass swing (module doc)."""
    inc = np.radians(inclination_deg)
    psi = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    u = np.stack([np.cos(inc) * np.cos(psi), -np.cos(inc) * np.sin(psi), -np.sin(inc) * np.ones_like(psi)], axis=1)
    raw = (field * u) @ np.linalg.inv(S_true).T + b_true
    cal = (raw - b) @ np.asarray(S).T
    err = np.angle(np.exp(1j * (np.arctan2(-cal[:, 1], cal[:, 0]) - psi)))
    return float(np.degrees(np.sqrt(np.mean(err * err))))


class Case:
    """One BROAD trial with the distortion applied: raw (finite rows), truth, clean mask, heading rows."""

    def __init__(self, root, key):
        self.key = key
        self.trial = load_trial(pathlib.Path(root) / TRIALS[key])
        self.b_true, self.S_true = distortion()
        ok = np.isfinite(self.trial["mag"]).all(axis=1)
        self.finite = ok
        self.raw_all = distort(np.where(ok[:, None], self.trial["mag"], 0.0), self.b_true, self.S_true)
        self.raw_all[~ok] = np.nan
        self.raw = self.raw_all[ok]                      # what a method is given: every finite sample
        self.clean_all = clean_mask(self.trial, undisturbed=(key == "03"))
        self.clean = self.clean_all[ok]
        self.rows = heading_rows(self.trial, self.clean_all)

    def errors(self, b, S, b_clean=None):
        out = {"hard_iron_err": float(np.linalg.norm(b - self.b_true)),
               "soft_iron_err": float(np.linalg.norm(S - self.S_true)),
               "heading_rms_deg": heading_error_rms(b, S, self.raw_all, self.trial, self.rows)}
        if b_clean is not None:
            out["hard_iron_vs_clean"] = float(np.linalg.norm(b - b_clean))
        return out


def main(argv=None):
    from mkc_stream import fit_ellipsoid

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default=str(REPO.parent / "shared" / "data" / "broad"))
    ap.add_argument("--trial", default="03,26")
    ap.add_argument("--methods", default="ls,mkc-em,mkc-em-geo,mkc-em-geo-dir")
    args = ap.parse_args(argv)
    for key in args.trial.split(","):
        c = Case(args.data_root, key)
        fl = fit_ellipsoid(c.raw[c.clean], "ls")
        print(f"trial {key}: {len(c.raw)} samples, {int(c.clean.sum())} known-clean, {len(c.rows[0])} heading rows")
        print(f"  truth (dataset cal.)   heading {heading_error_rms(c.b_true, c.S_true, c.raw_all, c.trial, c.rows):.3f} deg")
        print(f"  ls@clean               {c.errors(fl.hard_iron, fl.soft_iron)}")
        for m in args.methods.split(","):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t = time.perf_counter()
                f = fit_ellipsoid(c.raw, m)
                dt = time.perf_counter() - t
            e = c.errors(f.hard_iron, f.soft_iron, fl.hard_iron)
            print(f"  {m:<22} " + " ".join(f"{k} {v:.3f}" for k, v in e.items()) + f"  {dt * 1e3:.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
