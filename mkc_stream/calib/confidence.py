"""How much a window's data support one calibration over another, and how well they pin one down.

Both work on the field-strength residual of a calibration (b, S, F) over the window's raw samples,
    e_k = |S (m_k - b)| / F - 1                 (relative, so calibrations of different F compare)
over the samples a robust scale does not mark as disturbed (quality.outlier_mask).

Paired comparison (the streaming calibrator's switching rule). For a trial t and the accepted a,
    D_k = e_a,k^2 - e_t,k^2,   gain = mean(D)
over the trial's inliers, with a standard error clustered by direction cell (the 72 cells of the
trial-calibrated samples, quality.direction_cells):
    se^2 = G / (G - 1) * sum_c (sum_{k in c} (D_k - gain))^2 / n^2     (G occupied cells)
Samples of one direction share what the ellipsoid model does not fit there (a real sensor's field is
not an exact ellipsoid) and are taken close together in time, so they are not independent; samples
of different directions are closer to it. With the plain iid standard error the test fired on
nearly every trial of a steady real recording (docs/decisions/0016). gain > z se means the window
supports the trial as the better fit at about the one-sided normal level of z; the trial was fitted
to this window, but its in-sample advantage from fitting 9 parameters is small against z = 2.

Uncertainty (reported with an accepted calibration). Linearising the residual r_k = |S (m_k - b)| - F
in p = (b, s) (geometric.geometric_jacobian, F held as the scale), the least-squares covariance
    Cov(p) = s^2 (J^T J)^-1,   s^2 = sum r_k^2 / (n - 9)
over the inliers; the hard-iron standard deviations are the square roots of its first three diagonal
terms. The heading standard deviation is what that hard-iron uncertainty does to the heading of a
level sensor whose horizontal field is F (at the equator), averaged over headings:
    sd_heading = sqrt((Cov_xx + Cov_yy) / 2) / F   (radians; at inclination I divide by cos I).
It ignores correlation between samples, so it is a lower bound when they are correlated.
"""
from __future__ import annotations

import math

import numpy as np

from .geometric import geometric_jacobian, params_from_sym
from .quality import N_BANDS, N_SECTORS, direction_cells, outlier_mask

N_CELLS = N_BANDS * N_SECTORS

#: z of the paired test: a trial replaces the accepted calibration only when its gain is > Z_SWITCH se
Z_SWITCH = 2.0
#: z at which the pooled calibrator (streaming.py) counts a trial as disagreeing with its pool however
#: close the two are: W / K such trials in a row restart the pool
Z_RESTART = 3.0
#: the pooled calibrator restarts its pool at once from a trial the window supports at Z_RESTART whose
#: inliers the pool fits with a mean squared residual more than this many times the trial's (the pool's
#: RMS residual there over twice the trial's): the pool is then a wrong mode, not a window's noise
#: (on BROAD's real recordings the ratio of a supported trial stays near 1; wrong modes under heavy
#: synthetic bursts give 6-230)
DOMINANCE = 4.0


def relative_residuals(raw, b, S, F) -> np.ndarray:
    """e_k = |S (m_k - b)| / F - 1 for raw samples (N, 3)."""
    y = (np.asarray(raw, dtype=np.float64) - b) @ np.asarray(S).T
    return np.sqrt(np.einsum("ij,ij->i", y, y)) / float(F) - 1.0


def paired_gain(raw, trial, accepted):
    """(gain, se, n) of the trial over the accepted calibration on raw samples (module doc).

    trial, accepted: objects with hard_iron, soft_iron, field. gain > 0: the trial fits better.
    se is cluster-robust over the 72 direction cells of the trial-calibrated samples.
    """
    raw = np.asarray(raw, dtype=np.float64)
    et = relative_residuals(raw, trial.hard_iron, trial.soft_iron, trial.field)
    ea = relative_residuals(raw, accepted.hard_iron, accepted.soft_iron, accepted.field)
    keep = ~outlier_mask(et) & np.isfinite(et) & np.isfinite(ea)
    n = int(keep.sum())
    if n < 2:
        return 0.0, math.inf, n
    D = ea[keep] ** 2 - et[keep] ** 2
    gain = float(D.mean())
    cal = (raw[keep] - trial.hard_iron) @ np.asarray(trial.soft_iron).T
    norm = np.linalg.norm(cal, axis=1)
    cells = direction_cells(cal / np.maximum(norm, 1e-300)[:, None])
    sums = np.bincount(cells, weights=D - gain, minlength=N_CELLS)
    used = int((np.bincount(cells, minlength=N_CELLS) > 0).sum())
    if used < 2:
        return gain, math.inf, n
    # cluster-robust variance of the mean, with the small-sample factor G / (G - 1)
    se = math.sqrt(float(sums @ sums) * used / (used - 1)) / n
    return gain, se, n


def residual_ratio(raw, trial, accepted) -> float:
    """sum(e_a^2) / sum(e_t^2) over the trial's inliers (paired_gain's samples): how many times the
    accepted calibration's mean squared relative residual exceeds the trial's where the trial fits.
    inf when the trial fits them exactly and the accepted one does not; 1 without two inliers.
    The sums run in sample order, one term at a time, as the C port accumulates them beside the
    paired test's differences (confidence.c), so both take the same decision to the last bit."""
    raw = np.asarray(raw, dtype=np.float64)
    et = relative_residuals(raw, trial.hard_iron, trial.soft_iron, trial.field)
    ea = relative_residuals(raw, accepted.hard_iron, accepted.soft_iron, accepted.field)
    keep = ~outlier_mask(et) & np.isfinite(et) & np.isfinite(ea)
    if int(keep.sum()) < 2:
        return 1.0
    sa = st = 0.0
    for a, t in zip(ea[keep].tolist(), et[keep].tolist()):
        sa += a * a
        st += t * t
    if st > 0.0:
        return sa / st
    return math.inf if sa > 0.0 else 1.0


def supports_switch(raw, trial, accepted, z: float = Z_SWITCH) -> tuple:
    """(switch?, gain, se): the window supports replacing `accepted` by `trial` (module doc)."""
    gain, se, _ = paired_gain(raw, trial, accepted)
    return bool(gain > z * se), gain, se


def calibration_uncertainty(raw, b, S, F) -> dict:
    """{"hard_iron_sd": [3], "heading_sd_deg": x} of a calibration on raw samples (module doc), in the
    field's unit and degrees; NaN where the window cannot tell (too few inliers, singular J^T J)."""
    nan = {"hard_iron_sd": [math.nan] * 3, "heading_sd_deg": math.nan}
    raw = np.asarray(raw, dtype=np.float64)
    p = np.concatenate([np.asarray(b, dtype=np.float64), params_from_sym(S)])
    r, J = geometric_jacobian(p, raw, float(F))
    keep = ~outlier_mask(r) & np.isfinite(r) & np.isfinite(J).all(axis=1)
    n = int(keep.sum())
    if n <= 9 or not F > 0:
        return nan
    r, J = r[keep], J[keep]
    s2 = float(r @ r) / (n - 9)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return nan
    var_b = np.diag(cov)[:3]
    if not (np.isfinite(var_b).all() and (var_b >= 0).all()):
        return nan
    heading = math.degrees(math.sqrt(0.5 * (var_b[0] + var_b[1])) / float(F))
    return {"hard_iron_sd": [float(v) for v in np.sqrt(var_b)], "heading_sd_deg": heading}
