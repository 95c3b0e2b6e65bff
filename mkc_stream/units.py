"""Names of the magnetometer units a recording's ``units.mag`` may carry (docs/spec/recording.md).

One list for the reader (which warns about a unit it does not know) and the acceptance check (which
tests the fitted field against Earth's range only when the unit is microtesla).
"""
from __future__ import annotations

#: read as microtesla: the unit of the physical field-range check. Both the micro sign (U+00B5)
#: and the Greek mu (U+03BC) are written by real tools.
MICROTESLA = ("uT", "\u00b5T", "\u03bcT", "microtesla")
#: other units the spec names: the fit is the same, the field-range check does not apply
OTHER_MAG_UNITS = ("nT", "mG", "G", "gauss", "T", "counts", "raw", "LSB")


def is_microtesla(unit) -> bool:
    return isinstance(unit, str) and unit.strip().lower() in {u.lower() for u in MICROTESLA}
