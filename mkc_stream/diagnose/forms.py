"""The diagnoser's view of the effect library: each effect's fitting form, and what a form reads.

The forms themselves are declared by the effects, beside their forward models
(``Effect.form`` in :mod:`mkc_stream.sim.effects`); ``FORMS`` only indexes them by name, so an
effect added to the library is diagnosed without an edit here. This module holds what the
forms need from the diagnoser: :class:`Env`, the recording being diagnosed with the
diagnoser's own statistics (the forms live in the simulator's layer and cannot import them),
and the physical-range priors that keep a wrong form from "explaining" a gap with an absurd
coefficient.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..sim.effects import EFFECTS
from ..sim.effects.form import EstimatedForm, MeanForm
from ..sim.effects.nonlinear import F_REF, norm_pattern_rms
from ..sim.effects.noise_fit import block_mean_share, colored_white_share
from ..sim.effects.noise_fit import _block_mean_share_norm, _offsets, _variogram  # noqa: F401  (the tests read them here)
from ..sim.trajectory import moving_average
from .baseline import robust_sd
from .panel import _solve6, time_regressors

__all__ = ["EFFECTS", "FORMS", "PRIOR_FACTOR", "UNIT_TO_UT", "Env", "EstimatedForm", "MeanForm",
           "block_mean_share", "colored_white_share", "implausible", "norm_pattern_rms", "prior_bound"]

#: every effect's fitting form, by the effect's name (in the library's order)
FORMS = {name: effect.form for name, effect in EFFECTS.items()}

UNIT_TO_UT = {"uT": 1.0, "nT": 1e-3, "mT": 1e3, "T": 1e6, "G": 100.0, "gauss": 100.0, "Gauss": 100.0, "mG": 0.1}


@dataclass
class Env:
    """The recording a form is fitted to (``frame``), the baseline fit (``base``), a cache shared
    by the designs, and the diagnoser's statistics the forms reuse."""

    frame: object
    base: object
    cache: dict = field(default_factory=dict)

    @property
    def to_uT(self):
        return UNIT_TO_UT.get(self.frame.unit)

    @property
    def F_ref(self) -> float:
        """50 uT in the recording's unit, or the fitted field when the unit is unknown."""
        f = self.to_uT
        return F_REF / f if f else float(self.base.fit.state.F)

    def mdot(self):
        """dm/dt of the raw magnetometer (3-sample moving average first), unit/s."""
        if "mdot" not in self.cache:
            ms = moving_average(self.frame.m, 3)
            self.cache["mdot"] = np.gradient(ms, self.frame.t, axis=0)
        return self.cache["mdot"]

    def field_unit(self, x, nano=False):
        """(value, unit label) of a field-like quantity in the recording's unit."""
        f = self.to_uT
        if f is None:
            return float(x), self.frame.unit
        return float(x) * f * (1e3 if nano else 1.0), ("nT" if nano else "uT")

    def robust_sd(self, x) -> float:
        """Robust standard deviation (scaled MAD) of the finite values (:func:`.baseline.robust_sd`)."""
        return robust_sd(x)

    def time_regressors(self):
        """(N, 6) the panel's time-family regressors at the baseline's field directions."""
        if "time_regressors" not in self.cache:
            self.cache["time_regressors"] = time_regressors(self.base.fit.v)
        return self.cache["time_regressors"]

    def solve6(self, XX21, Xe):
        """The panel's ridge solve of its six regressors (:func:`.panel._solve6`)."""
        return _solve6(XX21, Xe)


# ---------------------------------------------------------------------------------------------
# physical-range priors
# ---------------------------------------------------------------------------------------------

#: A fitted deterministic effect whose size exceeds PRIOR_FACTOR times the top of the library's
#: realistic range (for a vector: its per-component top times sqrt(components)) is not a
#: physical explanation: a wrong form can close a gap by absorbing it with an absurd coefficient
#: (e.g. a current-induced offset "explained" as 4000 nT/degC of thermal offset). Such a fit is
#: reported but cannot be selected or counted as an alternative explanation.
PRIOR_FACTOR = 3.0


def prior_bound(name, magnitude):
    """(bound, unit) of the plausible size of a mean effect's magnitude dict, or None when the
    library gives no range in that unit (unknown recording unit, dimensionless settings)."""
    if not magnitude or magnitude.get("value") is None:
        return None
    unit = magnitude.get("unit")
    highs = [p.high for p in EFFECTS[name].params if p.unit == unit]
    if not highs:
        return None
    k = len(magnitude["vector"]) if isinstance(magnitude.get("vector"), list) else 1
    return PRIOR_FACTOR * max(highs) * np.sqrt(k), unit


def implausible(name, magnitude):
    """A text saying why a fitted magnitude is outside the physical range, or None."""
    b = prior_bound(name, magnitude)
    if b is None or not abs(float(magnitude["value"])) > b[0]:
        return None
    return (f"the fit needs {abs(float(magnitude['value'])):.3g} {b[1]}, beyond {PRIOR_FACTOR:g}x the realistic "
            f"range (<= {b[0]:.3g} {b[1]}): not a physical explanation")
