"""fit_ellipsoid: a batch magnetometer calibration with any of the package's regressors."""
from __future__ import annotations

import numpy as np

from .._validation import MKCInputError
from .ellipsoid import (EllipsoidFit, calibration_from_geometry, check_geometry_of_samples, design_matrix,
                        geometry_from_theta, gross_outlier_mask, normalisation_for, raw_geometry, robust_sphere_fit,
                        sphere_theta)
from .geometric import GeometricMKCEM
from .quality import quality_figures

#: Fixed bandwidth of method "mkc" (the paper's MKC column): weights exp(-e^2/(8 d^2)) halve at ~2.4 d.
MKC_FIXED_SIGMA = 2.0

CORE_METHODS = ("mkc-em", "mkc", "ls")
#: The geometric MKC-EM (calib/geometric.py), started from "mkc-em"; "-dir": with direction weighting.
GEOMETRIC_METHODS = ("mkc-em-geo", "mkc-em-geo-dir")


def available_methods():
    from ..baselines import BASELINES

    return list(CORE_METHODS) + list(GEOMETRIC_METHODS) + sorted(BASELINES)


def make_estimator(method: str, **params):
    """Estimator for a method name; params go to its constructor."""
    from ..batch import MKCRegressor, WLSRegressor

    key = method.lower()
    if key in GEOMETRIC_METHODS:
        return GeometricMKCEM(directions=key.endswith("-dir"), **params)
    if key in ("mkc-em", "mkcem", "em"):
        return MKCRegressor(em=True, **params)
    if key == "mkc":
        params.setdefault("sigma", MKC_FIXED_SIGMA)
        return MKCRegressor(em=False, **params)
    if key in ("ls", "wls", "lsq"):
        return WLSRegressor(**params)
    from ..baselines import BASELINES

    if key in BASELINES:
        return BASELINES[key](**params)
    raise MKCInputError(f"unknown method {method!r}; choose one of {', '.join(available_methods())}")


def _sample_weights(est, N):
    w = getattr(est, "weights_", None)
    if w is None and getattr(est, "inlier_mask_", None) is not None:
        w = np.asarray(est.inlier_mask_, dtype=np.float64)
    if w is None:
        return np.ones(N)
    w = np.asarray(w, dtype=np.float64).reshape(N, -1)[:, 0]
    return w


def weighted_condition(X: np.ndarray, w: np.ndarray) -> float:
    """cond of the Jacobi-equilibrated weighted normal matrix sum_k w_k x_k x_k^T."""
    Xw = X * np.sqrt(np.maximum(w, 0.0))[:, None]
    G = Xw.T @ Xw
    dg = np.sqrt(np.diag(G))
    if np.any(dg == 0):
        return float("inf")
    return float(np.linalg.cond(G / np.outer(dg, dg)))


MKC_METHODS = ("mkc-em", "mkcem", "em", "mkc")


def robust_start(mag: np.ndarray, norm) -> np.ndarray | None:
    """A high-breakdown start for the correntropy fits: the trimmed sphere fit, as theta in the
    normalised features (None: no sphere, start from WLS). Gross spikes (a shorted I2C line, a
    magnet) are high-leverage points of the quadratic features; from the WLS start they drag the
    fit to a 600 uT "field" with 15% of the samples at 300 uT, and no kernel recovers from there.
    """
    fit = robust_sphere_fit(mag) if mag.shape[0] >= 8 else None
    if fit is None:
        return None
    b, F = fit
    return sphere_theta((b - norm.offset) / norm.scale, F / norm.scale)


def fit_ellipsoid(mag, method: str = "mkc-em", *, estimator=None, **params) -> EllipsoidFit:
    """Fit the ellipsoid model (appendix, eqs. (36)-(40)) to raw magnetometer samples (N, 3).

    method: "mkc-em" (default), "mkc" (fixed sigma), "ls", "mkc-em-geo" / "mkc-em-geo-dir" (the
    geometric MKC-EM refinement of calib/geometric.py, without / with direction weighting), or a
    baseline name (see available_methods()); or pass a ready estimator with fit/coef_ (or a
    geometric.GeometricMKCEM). Returns hard iron b, soft iron S (symmetric positive definite),
    field F, per-sample weights and quality figures.
    Raises EllipsoidError when the data cannot give an ellipsoid, with the reason.
    """
    mag = np.asarray(mag, dtype=np.float64)
    if mag.ndim != 2 or mag.shape[1] != 3:
        raise MKCInputError(f"mag must have shape (N, 3); got {mag.shape}")
    if estimator is None and method.lower() in GEOMETRIC_METHODS:
        estimator = make_estimator(method, **params)
    if isinstance(estimator, GeometricMKCEM):    # it starts from "mkc-em", which validates mag
        return estimator.calibrate(mag)
    bad = ~np.isfinite(mag).all(axis=1)
    if bad.any():
        raise MKCInputError(f"{int(bad.sum())} sample(s) contain NaN or inf (first at row {int(np.flatnonzero(bad)[0])})")
    check_geometry_of_samples(mag)
    mkc = estimator is None and method.lower() in MKC_METHODS
    # MKC methods: samples no field explains (glitched reads thousands of times the field) are left
    # out of the fit, its start and its normalisation: their quadratic features would set the
    # E-step's truncation bound, and with it d's floor (see ellipsoid.GROSS_FACTOR). They keep
    # weight 0 and count as outliers in the quality figures; quality["gross_outliers"] is how many
    # were left out. The other methods (least squares, the baselines) see the data as given.
    gross = gross_outlier_mask(mag) if mkc else np.zeros(mag.shape[0], dtype=bool)
    fit_mag = mag[~gross] if gross.any() else mag
    if gross.any():
        check_geometry_of_samples(fit_mag)
    norm = normalisation_for(fit_mag)
    X = design_matrix(norm.apply(fit_mag))
    y = np.ones(fit_mag.shape[0])
    if mkc and "theta0" not in params:
        params["theta0"] = robust_start(fit_mag, norm)
    est = estimator if estimator is not None else make_estimator(method, **params)
    est.fit(X, y)
    theta = np.asarray(est.coef_, dtype=np.float64)
    geom = raw_geometry(geometry_from_theta(theta), norm)
    b, S, F = calibration_from_geometry(geom)
    w_fit = _sample_weights(est, fit_mag.shape[0])
    w = w_fit
    if gross.any():
        w = np.zeros(mag.shape[0])
        w[~gross] = w_fit
    with np.errstate(over="ignore", invalid="ignore"):     # the all-sample figures of a 1e300 read are inf
        m_cal = (mag - b) @ S.T
        quality = quality_figures(m_cal, F, weighted_condition(X, w_fit))
    quality["gross_outliers"] = int(gross.sum())
    channels = []
    if hasattr(est, "sigma_") and hasattr(est, "d_"):
        channels = [{"sigma": float(s), "d": float(d)} for s, d in zip(np.atleast_1d(est.sigma_), np.atleast_1d(est.d_))]
    name = method if estimator is None else type(estimator).__name__
    return EllipsoidFit(hard_iron=b, soft_iron=S, field=F, weights=w, quality=quality, method=name,
                        geometry=geom, theta_normalised=theta, normalisation=norm, channels=channels, estimator=est)
