"""What a recording can tell: whether its baseline is a calibration, and which statistics and
effects it can test.

The gap statistics and the effect tests read the residual of the baseline calibration. When
the calibrator would not accept that calibration (``calib.acceptance.evaluate``: too little of
the sphere covered, too many outliers, a fit error or a field out of range), the residual is
dominated by the calibration's own error (on a level flight the hard and soft iron along the
unvisited directions are not determined, and their second-order leftovers follow the attitude,
hence the throttle and the current): a gap read from it says nothing about the sensor. Then only
what does not rest on the calibration is tested: the raw values (their lattice and pile-ups)
and the timestamps, with the effects read there (quantization, saturation, timestamp jitter,
sample drops). Everything else is "not testable", with the calibrator's reason.

With an accepted calibration, a statistic that stands for an orientation-dependent effect needs
the orientations that effect needs: the quartic family (the scale nonlinearity's degree-4
pattern) needs the coverage the nonlinear forms need.
"""
from __future__ import annotations

from dataclasses import dataclass, field

#: panel families read from the raw values and the timestamps alone (no calibration)
CALIBRATION_FREE_FAMILIES = ("raw", "timing")
#: effects whose evidence lies in those families
CALIBRATION_FREE_EFFECTS = ("quantization", "saturation", "timestamp_jitter", "sample_drops")
#: panel family (before "/channel") -> the sphere coverage it needs (fraction of the 72 cells);
#: the same bar as the effect it stands for (scale_nonlinearity)
COVERAGE_FAMILIES = {"quartic": 0.5}


@dataclass
class Scope:
    accepted: bool                       # the calibrator would accept the baseline calibration
    rejection: object = None             # calib.result.Rejection when not accepted
    coverage: float = float("nan")       # of the 72 equal-area cells, by the baseline's directions
    quality: dict = field(default_factory=dict)

    @property
    def reason(self) -> str:
        return "" if self.rejection is None else self.rejection.text

    def family_reason(self, name: str):
        """Why a gap-index family (e.g. "quartic/norm", "raw") is not testable; None if it is."""
        family = name.split("/", 1)[0]
        if not self.accepted and family not in CALIBRATION_FREE_FAMILIES:
            return f"rests on the baseline calibration, which the calibrator rejects ({self.reason})"
        need = COVERAGE_FAMILIES.get(family)
        if need is not None and not self.coverage >= need:
            return f"orientations cover {self.coverage:.0%} of the sphere (needs >= {need:.0%})"
        return None

    def effect_testable(self, effect, evidence):
        """(testable, reason): the registry's own test, then the calibration's."""
        ok, why = effect.testable(evidence)
        if not self.accepted and effect.name not in CALIBRATION_FREE_EFFECTS:
            # both reasons when the recording also lacks what the effect needs
            return False, (f"its form reads the baseline calibration, which the calibrator rejects ({self.reason})"
                           + ("" if ok else f"; also, {why}"))
        if not ok:
            return False, why
        return True, why

    def tested(self) -> str:
        """What is still tested, in words (for the headline and the JSON)."""
        if self.accepted:
            return "everything the recording's excitation allows"
        return "the raw values (lattice, pile-ups) and the timestamps, and the effects read there (" \
            + ", ".join(CALIBRATION_FREE_EFFECTS) + ")"

    def to_json(self, off_families: dict, verdict_on_testable=None) -> dict:
        return {"calibration_accepted": self.accepted,
                "calibration_reason": self.reason or None,
                "coverage": self.coverage,
                "tested": self.tested(),
                "statistics_not_testable": dict(off_families),
                "verdict_on_testable": verdict_on_testable}


def baseline_scope(ellipsoid, unit: str, coverage: float, no_ellipsoid: str | None = None) -> Scope:
    """The calibrator's verdict on the baseline's calibration (its acceptance predicate, for the
    recording's unit), and the coverage of the baseline's directions. no_ellipsoid: why the samples
    gave no ellipsoid (the baseline is then a sphere stand-in, rejected with that reason)."""
    from ..calib.acceptance import AcceptanceRules, evaluate
    from ..calib.result import Rejection

    if no_ellipsoid is not None:
        return Scope(accepted=False, rejection=Rejection("not_ellipsoid", no_ellipsoid),
                     coverage=float(coverage), quality=dict(ellipsoid.quality))
    rejection = evaluate(ellipsoid.quality, float(ellipsoid.field), unit, AcceptanceRules())
    return Scope(accepted=rejection is None, rejection=rejection, coverage=float(coverage),
                 quality=dict(ellipsoid.quality))
