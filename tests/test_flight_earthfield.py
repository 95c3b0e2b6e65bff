"""The Earth field from WMM2025 (mkc_stream/flight/earthfield.py) against NOAA's published test values."""
import math
import sys

import numpy as np
import pytest

from mkc_stream._validation import MKCInputError
from mkc_stream.flight import earthfield as EF

pytest.importorskip("pygeomag")

# NOAA NCEI, WMM2025 test values (WMM2025_TEST_VALUES.txt, released with the model, Dec 2024:
# https://www.ncei.noaa.gov/sites/default/files/2025-02/WMM2025_TEST_VALUES.txt): decimal year,
# height above the WGS-84 ellipsoid (km), geodetic lat, lon (deg; 240 E = -120), X, Y, Z, H, F (nT), I, D (deg).
# Printed to 0.1 nT and 0.01 deg, which is the precision asserted.
NOAA_WMM2025 = [
    (2025.0, 0, 80, 0, 6521.6, 145.9, 54791.5, 6523.2, 55178.5, 83.21, 1.28),
    (2025.0, 0, 0, 120, 39677.8, -109.6, -10580.2, 39677.9, 41064.3, -14.93, -0.16),
    (2025.0, 0, -80, 240, 6117.5, 15751.9, -52022.5, 16898.1, 54698.2, -72.00, 68.78),
    (2025.0, 100, 80, 0, 6216.0, 92.4, 52598.8, 6216.7, 52964.9, 83.26, 0.85),
    (2025.0, 100, 0, 120, 37688.6, -96.2, -10152.1, 37688.7, 39032.1, -15.08, -0.15),
    (2025.0, 100, -80, 240, 5907.6, 14780.3, -49540.7, 15917.1, 52035.0, -72.19, 68.21),
    (2027.5, 0, 80, 0, 6500.8, 294.5, 54869.4, 6507.5, 55253.9, 83.24, 2.59),
    (2027.5, 0, 0, 120, 39701.6, -167.4, -10381.8, 39702.0, 41036.9, -14.65, -0.24),
    (2027.5, 0, -80, 240, 6200.7, 15730.3, -51783.7, 16908.3, 54474.2, -71.92, 68.49),
    (2027.5, 100, 80, 0, 6196.7, 233.8, 52670.5, 6201.1, 53034.3, 83.29, 2.16),
    (2027.5, 100, 0, 120, 37711.5, -148.7, -9969.8, 37711.8, 39007.4, -14.81, -0.23),
    (2027.5, 100, -80, 240, 5984.0, 14760.1, -49317.7, 15927.0, 51825.7, -72.10, 67.93),
]


@pytest.mark.parametrize("row", NOAA_WMM2025, ids=lambda r: f"{r[0]}-{r[1]}km-{r[2]}-{r[3]}")
def test_matches_noaa_test_values(row):
    year, hkm, lat, lon, X, Y, Z, H, F, incl, decl = row
    e = EF.earth_field(lat, lon, hkm * 1000.0, year)
    nt = e.ned_uT * 1000.0
    # half a unit of the last printed digit, plus float slack
    assert np.allclose(nt, [X, Y, Z], atol=0.051 + 1e-9)
    assert math.hypot(nt[0], nt[1]) == pytest.approx(H, abs=0.051)
    assert e.intensity_uT * 1000.0 == pytest.approx(F, abs=0.051)
    assert e.inclination_deg == pytest.approx(incl, abs=0.0051)
    assert e.declination_deg == pytest.approx(decl, abs=0.0051)
    assert e.to_json() == {"model": "WMM2025", "intensity": e.intensity_uT, "inclination_deg": e.inclination_deg,
                           "declination_deg": e.declination_deg}


def test_dates_and_positions_outside_the_model_are_refused():
    with pytest.raises(MKCInputError, match="2025-2030"):
        EF.earth_field(45.0, 7.0, 0.0, 2031.2)
    with pytest.raises(MKCInputError, match="2025-2030"):
        EF.earth_field(45.0, 7.0, 0.0, 2009.5)
    assert EF.earth_field(45.0, 7.0, 0.0, 2015.5).model == "WMM2015v2"      # an older log: the model of its epoch
    with pytest.raises(MKCInputError, match="latitude"):
        EF.earth_field(95.0, 7.0, 0.0, 2026.0)
    with pytest.raises(MKCInputError, match="ISO"):
        EF.earth_field(45.0, 7.0, 0.0, "yesterday")


def test_decimal_year_and_field_from_angles():
    assert EF.decimal_year("2026-07-02T12:00:00") == pytest.approx(2026 + 182.5 / 365, abs=1e-9)
    v = EF.field_from_angles(50.0, 60.0, 10.0)
    assert np.linalg.norm(v) == pytest.approx(50.0)
    assert math.degrees(math.atan2(v[2], math.hypot(v[0], v[1]))) == pytest.approx(60.0)
    assert math.degrees(math.atan2(v[1], v[0])) == pytest.approx(10.0)


def test_missing_pygeomag_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pygeomag", None)
    with pytest.raises(ImportError, match=r"mkc-stream\[wmm\]"):
        EF.earth_field(45.0, 7.0, 0.0, 2026.0)
