"""The Earth's main field at a position and date, from the World Magnetic Model WMM2025.

The model is evaluated by ``pygeomag`` (MIT licence, pure Python, no compiled parts, a port of
NOAA's reference C code): it ships NOAA's WMM2025 coefficients (epoch 2025.0, valid 2025.0-2030.0,
released 13 Nov 2024) and needs nothing else, so it installs anywhere the package does. Chosen over
NOAA's ``wmm-calculator`` for that and for its small, stable API (``GeoMag.calculate(glat, glon,
alt_km, decimal_year)``); its output matches NOAA's published WMM2025 test values to their printed
precision (tests/test_flight_earthfield.py). It lives behind the ``wmm`` extra.

Conventions: geodetic latitude and longitude in degrees, altitude in metres above the WGS-84
ellipsoid (pygeomag takes km); the field vector in north-east-down (NED) axes in uT (the model
gives nT); inclination positive downwards, declination positive east of true north, both degrees.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass

import numpy as np

from .._validation import MKCInputError

MODEL_NAME = "WMM2025"
#: The model's validity (decimal years); dates outside are refused rather than extrapolated.
VALID_FROM, VALID_TO = 2025.0, 2030.0
#: Earlier epochs that pygeomag ships, for logs recorded before 2025 (each valid 5 years from its
#: epoch; WMM2015v2 is NOAA's out-of-cycle 2015 release). Only WMM2025 is tested against NOAA's values.
EARLIER = {2010: ("WMM2010", "wmm/WMM_2010.COF"), 2015: ("WMM2015v2", "wmm/WMM_2015v2.COF"),
           2020: ("WMM2020", "wmm/WMM_2020.COF")}
WMM_EXTRA_HINT = 'the Earth-field model needs pygeomag: pip install "mkc-stream[wmm]"'


@dataclass(frozen=True)
class EarthField:
    """The main field at one place and time: NED vector and its angles (see module doc for units)."""

    ned_uT: np.ndarray            # (3,) north, east, down, uT
    intensity_uT: float           # |ned|
    inclination_deg: float        # atan2(down, horizontal)
    declination_deg: float        # atan2(east, north)
    lat_deg: float
    lon_deg: float
    alt_m: float
    decimal_year: float
    model: str = MODEL_NAME

    def to_json(self) -> dict:
        """The ``earth_field`` object of docs/spec/machine-output.md (intensity in uT)."""
        return {"model": self.model, "intensity": float(self.intensity_uT),
                "inclination_deg": float(self.inclination_deg), "declination_deg": float(self.declination_deg)}


def decimal_year(date) -> float:
    """A decimal year from a float/int year, a datetime.date/datetime, or an ISO date string."""
    if isinstance(date, (int, float)) and not isinstance(date, bool):
        return float(date)
    if isinstance(date, str):
        try:
            date = _dt.datetime.fromisoformat(date)
        except ValueError as e:
            raise MKCInputError(f"date must be a decimal year or an ISO date (YYYY-MM-DD); got {date!r}") from e
    if isinstance(date, _dt.date) and not isinstance(date, _dt.datetime):
        date = _dt.datetime(date.year, date.month, date.day)
    if not isinstance(date, _dt.datetime):
        raise MKCInputError(f"date must be a decimal year, a date or an ISO date string; got {date!r}")
    start = _dt.datetime(date.year, 1, 1, tzinfo=date.tzinfo)
    end = _dt.datetime(date.year + 1, 1, 1, tzinfo=date.tzinfo)
    return date.year + (date - start).total_seconds() / (end - start).total_seconds()


def _geomag(coefficients="wmm/WMM_2025.COF"):
    try:
        from pygeomag import GeoMag
    except ImportError as e:
        raise ImportError(WMM_EXTRA_HINT) from e
    return GeoMag(coefficients_file=coefficients)


def earth_field(lat_deg, lon_deg, alt_m=0.0, date=None) -> EarthField:
    """WMM2025 (WMM2010-2020 for earlier dates) at geodetic (lat_deg, lon_deg, alt_m above the ellipsoid) on ``date`` (decimal year,
    date, datetime or ISO string; today when None). Raises MKCInputError for a position or date the
    model does not cover, ImportError naming the ``wmm`` extra when pygeomag is missing."""
    lat, lon, alt = float(lat_deg), float(lon_deg), float(alt_m)
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise MKCInputError(f"latitude must be within [-90, 90] degrees; got {lat_deg!r}")
    if not math.isfinite(lon):
        raise MKCInputError(f"longitude must be finite (degrees); got {lon_deg!r}")
    lon = (lon + 180.0) % 360.0 - 180.0
    # WMM's stated altitude range: -1 km to 850 km above the ellipsoid
    if not (math.isfinite(alt) and -1000.0 <= alt <= 850e3):
        raise MKCInputError(f"altitude must be within [-1000, 850000] m of the WGS-84 ellipsoid; got {alt_m!r}")
    year = decimal_year(_dt.datetime.now(_dt.timezone.utc) if date is None else date)
    model, cof = MODEL_NAME, "wmm/WMM_2025.COF"
    epoch = int(5 * math.floor(year / 5.0))
    if epoch in EARLIER:
        model, cof = EARLIER[epoch]
    elif not VALID_FROM <= year < VALID_TO:
        raise MKCInputError(f"{MODEL_NAME} covers {VALID_FROM:g}-{VALID_TO:g} (earlier epochs from 2010); the date "
                            f"{year:.3f} is outside (give the flight's date, or a field reference)")
    r = _geomag(cof).calculate(glat=lat, glon=lon, alt=alt / 1000.0, time=year)
    ned = np.array([r.x, r.y, r.z], dtype=np.float64) / 1000.0           # nT -> uT
    return EarthField(ned_uT=ned, intensity_uT=float(np.linalg.norm(ned)), inclination_deg=float(r.i),
                      declination_deg=float(r.d), lat_deg=lat, lon_deg=lon, alt_m=alt, decimal_year=year, model=model)


def field_from_angles(intensity, inclination_deg, declination_deg=0.0) -> np.ndarray:
    """NED vector of a field of the given intensity, inclination and declination (same unit as intensity)."""
    i, d = math.radians(inclination_deg), math.radians(declination_deg)
    return float(intensity) * np.array([math.cos(i) * math.cos(d), math.cos(i) * math.sin(d), math.sin(i)])
