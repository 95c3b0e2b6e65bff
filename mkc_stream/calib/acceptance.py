"""One readable acceptance predicate for a magnetometer calibration (trial vs accepted).

Like the embedded peers' fit-acceptable gates: a calibration is used only when every criterion
holds, and a rejection names each criterion that failed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import MKCInputError
from ..units import is_microtesla
from .result import Rejection

#: Earth's field is 22-67 uT at the surface; wider bounds leave room for local anomalies.
EARTH_FIELD_UT = (15.0, 100.0)


@dataclass(frozen=True)
class AcceptanceRules:
    min_coverage: float = 0.5              # of the 72 equal-area direction cells
    max_condition: float = 1e6             # of the equilibrated weighted normal matrix
    max_outlier_fraction: float = 0.4      # a disturbance-dominated window is not a calibration
    # inlier |m_cal| - F rms relative to F: catches a model that does not fit (a disturbance-dominated
    # window, the wrong sensor axis order). Cheap sensors are noisy (the QMC5883L demo: 6.2% rms), and
    # noise alone does not bias a fit over thousands of samples, so the gate is 10%, not the 3-5% of
    # peers tuned for quiet sensors.
    max_residual_rel: float = 0.10
    field_range_ut: tuple = EARTH_FIELD_UT # checked only when the unit is known to be uT
    # Streaming only: before a new calibration is accepted, a cold start (WLS, then MKC-EM) on the
    # same window must agree with the warm-started trial, hard iron and field within this fraction
    # of the field. A warm-started estimate can lock onto a wrong mode that it reinforces (the
    # samples it down-weights are exactly the ones that would correct it); a cold start cannot
    # inherit that. Agreement is ~0.1% of F when both are right.
    max_disagreement_rel: float = 0.02

    def __post_init__(self):
        # A NaN threshold makes every comparison fail: every trial would be rejected, forever,
        # with a reason like "coverage 85% < nan%". inf is allowed for the upper limits (no limit).
        def bad(name, ok):
            if not ok:
                raise MKCInputError(f"AcceptanceRules.{name} out of range: {getattr(self, name)!r}")

        num = lambda v: isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)  # noqa: E731
        for name in ("min_coverage", "max_condition", "max_outlier_fraction", "max_residual_rel", "max_disagreement_rel"):
            bad(name, num(getattr(self, name)) and not np.isnan(getattr(self, name)))
        bad("min_coverage", 0 <= self.min_coverage <= 1)
        bad("max_outlier_fraction", 0 <= self.max_outlier_fraction <= 1)
        bad("max_condition", self.max_condition >= 1)
        bad("max_residual_rel", self.max_residual_rel > 0)
        bad("max_disagreement_rel", self.max_disagreement_rel >= 0)
        fr = self.field_range_ut
        bad("field_range_ut", isinstance(fr, (tuple, list)) and len(fr) == 2 and all(num(v) for v in fr)
            and 0 <= fr[0] < fr[1])


# The rejection sentences, one function each: check() below and the C port's reason codes
# (mkc_stream.cport.bindings.reason_text) format them here, so a Python and a C rejection read the same.

def coverage_failure(cov, rules: AcceptanceRules) -> str:
    return f"sphere coverage {cov:.0%} < {rules.min_coverage:.0%}: rotate the sensor through more orientations"


def condition_failure(cond, rules: AcceptanceRules) -> str:
    return f"condition number {cond:.3g} > {rules.max_condition:.3g}"


def outlier_failure(out, rules: AcceptanceRules) -> str:
    return f"outlier fraction {out:.0%} > {rules.max_outlier_fraction:.0%}: too much disturbance"


#: a fit error above this share of the field, with a fitted field below the physical range, is a
#: cloud of samples around one point (a sensor that barely turned: the norm of a 3-D Gaussian cloud
#: about its centre spreads by ~42% of its mean), not a sphere with disturbances
CLOUD_RESIDUAL_REL = 0.3


def residual_failure(rel, rules: AcceptanceRules, field_below_range: bool = False) -> str:
    text = f"fit error {rel:.1%} of the field > {rules.max_residual_rel:.0%}"
    if field_below_range and rel > CLOUD_RESIDUAL_REL:
        text += (" (the samples are a cloud around one point, not a sphere: the sensor barely turned; "
                 "rotate it through all axes)")
    return text


def field_range_failure(field, rules: AcceptanceRules) -> str:
    lo, hi = rules.field_range_ut
    return f"fitted field {field:.1f} uT outside the physical range [{lo:g}, {hi:g}] uT"


def field_nonpositive_failure(field) -> str:
    return f"fitted field {field} is not a positive number"


def disagreement_failure(disagreement, rules: AcceptanceRules) -> str:
    return (f"not confirmed: a cold start on the same window differs by {disagreement:.3g} "
            f"(> {rules.max_disagreement_rel:.0%} of the field); continuing from the cold start")


# The streaming calibrator's two waiting sentences before its final feature normalisation.

def motion_wait_reason(spread, limit) -> str:
    return (f"waiting for motion: the window is a cloud around one point (spread {spread:.0%} of its "
            f"radius > {limit:.0%}), not a sphere: rotate the sensor through all axes")


def degenerate_reason() -> str:
    return ("the samples do not determine an ellipsoid (normal equations singular: they lie on a curve or "
            "a plane): rotate the sensor through all axes")


def coverage_wait_reason(cov, limit) -> str:
    return (f"waiting for orientation coverage ({cov:.0%} of the sphere around a sphere fit "
            f"< {limit:.0%}): rotate the sensor through all axes")


#: the checks of the predicate, in its order (Rejection.failed names them)
CHECKS = ("coverage", "condition", "outliers", "residual", "field_range", "field_nonpositive", "disagreement")


def evaluate(quality: dict, field: float, unit: str = "uT", rules: AcceptanceRules = AcceptanceRules(),
             disagreement=None):
    """None when the calibration is accepted, else the Rejection naming every failed check.

    disagreement: the streaming calibrator's cold-start check, max(|b - b_cold|, |F - F_cold|) in
    the unit of the field (None: not checked).
    """
    cov = quality.get("coverage", 0.0)
    cond = quality.get("condition", np.inf)
    out = quality.get("outlier_fraction", 1.0)
    rel = quality.get("residual_rms", np.inf) / field if field > 0 else np.inf
    failed = []
    if not cov >= rules.min_coverage:
        failed.append(("coverage", coverage_failure(cov, rules)))
    if not cond <= rules.max_condition:
        failed.append(("condition", condition_failure(cond, rules)))
    if not out <= rules.max_outlier_fraction:
        failed.append(("outliers", outlier_failure(out, rules)))
    if not rel <= rules.max_residual_rel:
        below = is_microtesla(unit) and field < rules.field_range_ut[0]
        failed.append(("residual", residual_failure(rel, rules, below)))
    if is_microtesla(unit):
        lo, hi = rules.field_range_ut
        if not lo <= field <= hi:
            failed.append(("field_range", field_range_failure(field, rules)))
    elif not (np.isfinite(field) and field > 0):
        failed.append(("field_nonpositive", field_nonpositive_failure(field)))
    if disagreement is not None and not disagreement <= rules.max_disagreement_rel * abs(field):
        failed.append(("disagreement", disagreement_failure(disagreement, rules)))
    if not failed:
        return None
    values = {"coverage": cov, "condition": cond, "outlier_fraction": out, "residual_rel": rel, "field": field}
    if disagreement is not None:
        values["disagreement"] = disagreement
    return Rejection("rejected", "; ".join(t for _, t in failed), tuple(n for n, _ in failed), values)


def check(quality: dict, field: float, unit: str = "uT", rules: AcceptanceRules = AcceptanceRules(),
          disagreement=None):
    """(accepted, reason): evaluate() as a flag and the sentence ('' when accepted)."""
    rejection = evaluate(quality, field, unit, rules, disagreement)
    return rejection is None, "" if rejection is None else rejection.text
