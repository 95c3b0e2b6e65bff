"""The text report of a calibration (calib/result.py Calibration), one for every command.

`calibrate` (batch and --stream), `live` and `replay` print a calibration, or why there is none,
with these lines; their JSON is Calibration.to_json / result.no_calibration_json.
"""
from __future__ import annotations

import math

from .common import fmt_vec


def calibration_lines(cal, unit: str, *, first_accepted_at=None, kernel_note: str = "") -> list:
    """The report lines of a calibration, accepted or not (then its rejection closes them)."""
    lines = [f"  method        : {cal.method}"]
    if first_accepted_at is not None:
        lines.append(f"  first accepted: after {first_accepted_at} samples")
    lines.append(f"  hard iron b   : {fmt_vec(cal.hard_iron, unit)}")
    S = cal.soft_iron
    lines += [f"  soft iron S   : {fmt_vec(S[0], '')}", f"                  {fmt_vec(S[1], '')}",
              f"                  {fmt_vec(S[2], '')}   (m_cal = S (m_raw - b), det S = 1)"]
    lines.append(f"  field F       : {cal.field:.5g} {unit}")
    if cal.channels:
        lines.append(f"  kernel        : sigma {cal.sigma:.4g}, d {cal.d:.4g}{kernel_note}")
    q = cal.quality
    line = f"  quality       : inlier residual rms {q['residual_rms']:.4g} {unit} ({q['residual_rms'] / cal.field:.2%} of F)"
    if "norm_spread" in q:
        line += f", norm spread {q['norm_spread_inliers']:.2%} (inliers) / {q['norm_spread']:.2%} (all)"
    lines.append(line)
    lines.append(f"                  sphere coverage {q['coverage']:.0%}, outliers {q['outlier_fraction']:.1%}, "
                 f"condition {q['condition']:.3g}")
    u = cal.uncertainty
    if u and all(math.isfinite(v) for v in u["hard_iron_sd"]):
        lines.append(f"  uncertainty   : hard iron sd {fmt_vec(u['hard_iron_sd'], unit)}, heading sd "
                     f"{u['heading_sd_deg']:.2f} deg (level, horizontal field = F; lower bounds: samples taken "
                     f"as independent)")
    lines.append(status_line(cal.rejection))
    return lines


def status_line(rejection) -> str:
    """'  status        : ACCEPTED' or 'REJECTED - why' (rejection: calib/result.py Rejection or None)."""
    return "  status        : ACCEPTED" if rejection is None else f"  status        : REJECTED - {rejection.text}"
