"""mkc_stream: robust, live IMU calibration with multi-kernel correntropy EM regression.

`import mkc_stream` stays light: numba kernels compile on first use (cached on disk).
"""
__version__ = "0.1.0"

_LAZY = {
    "MKCRegressor": "mkc_stream.batch",
    "WLSRegressor": "mkc_stream.batch",
    "mkc_loss": "mkc_stream.batch",
    "MKCInputError": "mkc_stream._validation",
    "mkc_pdf": "mkc_stream.pdf",
    "mkc_logpdf": "mkc_stream.pdf",
    "robustness_bound": "mkc_stream.bounds",
    "optimal_sigma": "mkc_stream.bounds",
    "fit_ellipsoid": "mkc_stream.calib.fit",
    "EllipsoidError": "mkc_stream.calib.ellipsoid",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mkc_stream' has no attribute {name!r}")
