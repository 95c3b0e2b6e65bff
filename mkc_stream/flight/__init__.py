"""Calibration from a flight or robot log: the Earth field (WMM2025), the attitude-aided robust vector
fit with current/throttle compensation and its delay, and a yaw-only mode (docs/flight.md).

``fit_flight(recording, ...)`` returns a FlightCalibration whose ``to_json()`` holds the
``compensation`` and ``earth_field`` objects of docs/spec/machine-output.md.
"""
from .calibrate import FlightCalibration, fit_flight
from .earthfield import EarthField, earth_field
from .vector_fit import VectorFit, VectorFitSettings, fit_vector

__all__ = ["EarthField", "FlightCalibration", "VectorFit", "VectorFitSettings", "earth_field", "fit_flight",
           "fit_vector"]
