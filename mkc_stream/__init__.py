"""mkc_stream: robust, live IMU calibration with multi-kernel correntropy EM regression.

`import mkc_stream` stays light: numba kernels compile on first use (cached on disk).
"""
__version__ = "0.1.0"

#: name -> the module it comes from, imported on first use (PEP 562): `import mkc_stream` loads
#: neither numba, scipy nor matplotlib
_LAZY = {
    # streaming estimator and magnetometer calibration
    "StreamingMKC": "mkc_stream.stream",
    "StreamSnapshot": "mkc_stream.stream",
    "MagCalibrator": "mkc_stream.calib.streaming",
    "Calibration": "mkc_stream.calib.result",
    "CheckpointEvent": "mkc_stream.calib.streaming",
    "NotCalibratedError": "mkc_stream.calib.streaming",
    "AcceptanceRules": "mkc_stream.calib.acceptance",
    "fit_ellipsoid": "mkc_stream.calib.fit",
    "EllipsoidError": "mkc_stream.calib.ellipsoid",
    # batch regression
    "MKCRegressor": "mkc_stream.batch",
    "WLSRegressor": "mkc_stream.batch",
    "mkc_loss": "mkc_stream.batch",
    "MKCInputError": "mkc_stream._validation",
    "mkc_pdf": "mkc_stream.pdf",
    "mkc_logpdf": "mkc_stream.pdf",
    "robustness_bound": "mkc_stream.bounds",
    "optimal_sigma": "mkc_stream.bounds",
    # recordings, live sources, simulator
    "Recording": "mkc_stream.io.recording",
    "RecordingError": "mkc_stream.io.recording",
    "read_recording": "mkc_stream.io.recording",
    "write_recording": "mkc_stream.io.recording",
    "open_source": "mkc_stream.ingest.opener",
    "simulate": "mkc_stream.sim",
    "SensorModel": "mkc_stream.sim",
    "Trajectory": "mkc_stream.sim",
}

#: subpackages exported by name. `diagnose` is the subpackage, not its function: the import system
#: sets the attribute `mkc_stream.diagnose` to the subpackage whenever any of its modules is
#: imported, so a function of that name here would not stay one. Call mkc_stream.diagnose.diagnose(recording).
_SUBPACKAGES = ("diagnose",)

__all__ = sorted([*_LAZY, *_SUBPACKAGES]) + ["__version__"]


from ._lazy import lazy_exports  # noqa: E402

__getattr__, __dir__ = lazy_exports(__name__, _LAZY, _SUBPACKAGES)
