"""Magnetometer (and later accelerometer/gyroscope) calibrators, quality metrics and gates."""

#: name -> the module it comes from, imported on first use (PEP 562)
_LAZY = {
    "MagCalibrator": "mkc_stream.calib.streaming",
    "Calibration": "mkc_stream.calib.streaming",
    "CheckpointEvent": "mkc_stream.calib.streaming",
    "NotCalibratedError": "mkc_stream.calib.streaming",
    "AcceptanceRules": "mkc_stream.calib.acceptance",
    "fit_ellipsoid": "mkc_stream.calib.fit",
    "EllipsoidError": "mkc_stream.calib.ellipsoid",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'mkc_stream.calib' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
