"""The one calibration result of the package, batch or streamed, and why one was not accepted.

``Calibration`` is what `fit_ellipsoid(...).calibration(...)`, ``MagCalibrator.trial`` /
``.accepted`` and the C port's wrapper (``CMagCalibrator``) return; ``Rejection`` says why a
calibration (or none) was not accepted: a code, the failed checks by name and their values, and the
sentence a person reads. ``to_json`` writes the `calibrate` object of docs/spec/machine-output.md,
and ``no_calibration_json`` the same object when there is no calibration at all.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..jsonout import jsonable

#: the quality figures of docs/spec/machine-output.md, null when there is no calibration
EMPTY_QUALITY = {"residual_rms": None, "coverage": None, "outlier_fraction": None, "condition": None}

#: Rejection codes: "rejected" (the acceptance predicate failed: see `failed`), "warming_up" (not
#: enough samples yet), "waiting_motion" / "waiting_coverage" (the stream waits before its final
#: normalisation), "not_ellipsoid" (the fit gives no ellipsoid), "no_calibration" (a run without one)
REJECTION_CODES = ("rejected", "warming_up", "waiting_motion", "waiting_coverage", "not_ellipsoid", "no_calibration")


@dataclass(frozen=True)
class Rejection:
    code: str
    text: str
    #: names of the failed checks (acceptance.CHECKS), in the predicate's order
    failed: tuple = ()
    #: the figures the checks compared, by check name
    values: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"code": self.code, "failed": list(self.failed), "values": jsonable(self.values)}


@dataclass(frozen=True)
class Calibration:
    """m_cal = S (m_raw - b), det S = 1, |m_cal| = F when undisturbed."""

    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field: float
    quality: dict
    accepted: bool
    rejection: Optional[Rejection] = None
    method: str = "mkc-em-stream"
    #: [{"sigma": s, "d": d}] per residual channel, [] for methods without a kernel
    channels: list = field(default_factory=list)
    #: {"hard_iron_sd": [3], "heading_sd_deg"} (calib/confidence.py), None when not computed
    uncertainty: Optional[dict] = None
    samples_seen: int = 0
    esteps: int = 0

    @property
    def reason(self) -> str:
        """'' when accepted, else the sentence naming every failed check."""
        return "" if self.rejection is None else self.rejection.text

    @property
    def sigma(self) -> float:
        return float(self.channels[0]["sigma"]) if self.channels else float("nan")

    @property
    def d(self) -> float:
        return float(self.channels[0]["d"]) if self.channels else float("nan")

    def apply(self, raw):
        return (np.asarray(raw, dtype=np.float64) - self.hard_iron) @ self.soft_iron.T

    def to_json(self, counts=None) -> dict:
        out = {"hard_iron": [float(v) for v in self.hard_iron],
               "soft_iron": [[float(v) for v in r] for r in self.soft_iron],
               "field": float(self.field),
               "channels": [{"sigma": jsonable(c.get("sigma")), "d": jsonable(c.get("d"))} for c in self.channels],
               "quality": jsonable(self.quality),
               "status": "accepted" if self.accepted else "rejected",
               "reason": None if self.accepted else self.reason,
               "counts": counts, "method": self.method, "uncertainty": jsonable(self.uncertainty)}
        if self.rejection is not None:
            out["rejection"] = self.rejection.to_json()
        return out


def no_calibration_json(rejection: Rejection, counts=None, method=None) -> dict:
    """The `calibrate` object when there is no calibration to report (nulls, and why)."""
    out = {"hard_iron": None, "soft_iron": None, "field": None, "channels": [], "quality": dict(EMPTY_QUALITY),
           "status": "rejected", "reason": rejection.text, "counts": counts, "rejection": rejection.to_json()}
    if method is not None:
        out["method"] = method
    return out
