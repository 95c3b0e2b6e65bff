"""Several compasses of one flight, each calibrated (calibrate.fit_flight), compared with each other.

For each compass k, its calibrated field in the navigation frame over the flight is
    e_k(t) = R(q(t)) S_k (m_k(t) - b_k - K_k c(t - tau_k)) / g_k        (uT, north-east-down)
with R(q) the log's attitude (body -> NED), g_k its fitted gain (sensor unit per uT; 1 without a
field model), and its magnetic heading psi_k(t) = atan2(e_east, e_north). Compared on compass 0's
times (the others interpolated onto them):
  - field: the median |e_k| against the model's intensity (when the log has a position);
  - heading: the RMS of psi_i - psi_j for each pair of compasses;
  - a compass is named inconsistent when its heading differs from every other compass's by more than
    HEADING_TOL_DEG and by more than twice what the others differ among themselves (it disagrees
    alone: it takes three compasses to tell which), or its field is off the model by more than
    FIELD_TOL of it.
"""
from __future__ import annotations

import math

import numpy as np

from .delay import delayed
from .vector_fit import rotation_matrices

QUAT = ("qw", "qx", "qy", "qz")
#: heading RMS (deg) against the other compasses above which one can be named inconsistent
HEADING_TOL_DEG = 2.0
#: relative difference from the model's intensity above which a compass is named inconsistent
FIELD_TOL = 0.15


def navigation_field(rec, fc) -> tuple:
    """(t, e (N, 3) uT north-east-down) of a flight calibration fc applied to its recording rec."""
    q = np.stack([rec.aux[c] for c in QUAT], axis=1)
    m = np.asarray(rec.mag, dtype=np.float64).copy()
    for coeff, name in ((fc.current, "current"), (fc.throttle, "throttle")):
        if coeff is not None and name in rec.aux:
            c = np.asarray(rec.aux[name], dtype=np.float64)[:, None]
            m -= delayed(rec.t, np.nan_to_num(c), fc.delay_s or 0.0) @ np.asarray(coeff)[None, :]
    cal = (m - fc.hard_iron) @ fc.soft_iron.T
    gain = fc.scale if math.isfinite(fc.scale) and fc.scale > 0 else 1.0
    ok = np.isfinite(q).all(axis=1) & np.isfinite(cal).all(axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    R = rotation_matrices(np.where(ok[:, None], q, [1.0, 0.0, 0.0, 0.0]))
    e = np.einsum("kij,kj->ki", R, cal) / gain
    e[~ok] = np.nan
    return np.asarray(rec.t, dtype=np.float64), e


def compare_compasses(items, intensity_uT=None) -> dict:
    """items: [(id, rec, fc)] of accepted flight calibrations. Returns the comparison (module doc)."""
    if len(items) < 2:
        return {"compasses": [], "inconsistent": [], "note": "fewer than two calibrated compasses: nothing to compare"}
    t0, _ = navigation_field(items[0][1], items[0][2])
    headings, fields = [], []
    for _, rec, fc in items:
        t, e = navigation_field(rec, fc)
        e_on = np.stack([np.interp(t0, t, e[:, j], left=np.nan, right=np.nan) for j in range(3)], axis=1)
        headings.append(np.arctan2(e_on[:, 1], e_on[:, 0]))
        fields.append(float(np.nanmedian(np.linalg.norm(e, axis=1))))
    H = np.array(headings)
    n = len(items)
    D = np.zeros((n, n))                      # heading RMS (deg) between each pair of compasses
    for i in range(n):
        for j in range(i + 1, n):
            d = np.angle(np.exp(1j * (H[i] - H[j])))
            d = d[np.isfinite(d)]
            D[i, j] = D[j, i] = float(np.degrees(np.sqrt(np.mean(d * d)))) if d.size else math.nan
    rows = []
    for k, (cid, _, _) in enumerate(items):
        row = {"id": cid, "heading_rms_deg": {items[j][0]: D[k, j] for j in range(n) if j != k},
               "field_uT": fields[k]}
        if intensity_uT:
            row["field_vs_model"] = fields[k] / float(intensity_uT) - 1.0
        rows.append(row)
    bad, note = [], None
    for k, row in enumerate(rows):
        closest = float(np.min(np.delete(D[k], k)))
        others = [D[i, j] for i in range(n) for j in range(i + 1, n) if k not in (i, j)]
        # alone: far from every other compass, while the others agree more closely among themselves
        alone = closest > HEADING_TOL_DEG and bool(others) and closest > 2.0 * max(others)
        off_model = abs(row.get("field_vs_model", 0.0)) > FIELD_TOL
        if alone or off_model:
            why = []
            if alone:
                why.append(f"its heading differs from every other compass's by {closest:.1f} deg RMS or more")
            if off_model:
                why.append(f"its field is {row['field_vs_model']:+.0%} from the model")
            bad.append({"id": row["id"], "reason": "; ".join(why)})
    if n == 2 and D[0, 1] > HEADING_TOL_DEG:
        note = f"the two compasses' headings differ by {D[0, 1]:.1f} deg RMS; two cannot tell which is wrong"
    out = {"compasses": rows, "inconsistent": bad}
    if note:
        out["note"] = note
    return out
