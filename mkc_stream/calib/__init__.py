"""Magnetometer (and later accelerometer/gyroscope) calibrators, quality metrics and gates."""

#: name -> the module it comes from, imported on first use (PEP 562)
_LAZY = {
    "MagCalibrator": "mkc_stream.calib.streaming",
    "Calibration": "mkc_stream.calib.result",
    "Rejection": "mkc_stream.calib.result",
    "CheckpointEvent": "mkc_stream.calib.streaming",
    "NotCalibratedError": "mkc_stream.calib.streaming",
    "AcceptanceRules": "mkc_stream.calib.acceptance",
    "fit_ellipsoid": "mkc_stream.calib.fit",
    "EllipsoidError": "mkc_stream.calib.ellipsoid",
}

__all__ = sorted(_LAZY)


from .._lazy import lazy_exports  # noqa: E402

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
