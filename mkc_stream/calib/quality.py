"""Quality figures of a magnetometer calibration (method independent, physical units)."""
from __future__ import annotations

import numpy as np

from ..robust import mad_sd

#: Equal-area direction cells: 6 bands uniform in z (= sin latitude) x 12 sectors of 30 degrees.
N_BANDS = 6
N_SECTORS = 12


def direction_cells(unit: np.ndarray) -> np.ndarray:
    """Cell index (0..71) of each unit vector (N, 3) on the equal-area 72-cell sphere grid."""
    z = np.clip(unit[:, 2], -1.0, 1.0)
    band = np.minimum(((z + 1.0) * 0.5 * N_BANDS).astype(np.int64), N_BANDS - 1)
    lon = np.arctan2(unit[:, 1], unit[:, 0]) + np.pi
    sector = np.minimum((lon / (2 * np.pi) * N_SECTORS).astype(np.int64), N_SECTORS - 1)
    return band * N_SECTORS + sector


def sphere_coverage(m_cal: np.ndarray, mask=None) -> float:
    """Fraction of the 72 equal-area direction cells that hold at least one sample."""
    v = m_cal if mask is None else m_cal[mask]
    n = np.linalg.norm(v, axis=1)
    ok = n > 0
    if not ok.any():
        return 0.0
    cells = direction_cells(v[ok] / n[ok, None])
    return float(np.unique(cells).size) / (N_BANDS * N_SECTORS)


def sphere_spread(mag: np.ndarray, centre, radius) -> float:
    """Robust scale of |m - centre| - radius relative to the radius (inf for a radius <= 0)."""
    if not radius > 0:
        return float("inf")
    return float(mad_sd(np.linalg.norm(mag - np.asarray(centre), axis=1) - radius)) / float(radius)


def norm_residuals(m_cal: np.ndarray, field: float) -> np.ndarray:
    return np.linalg.norm(m_cal, axis=1) - field


def outlier_mask(resid: np.ndarray, k: float = 3.5) -> np.ndarray:
    """|r - median| > k * 1.4826 MAD: the samples a robust scale marks as disturbed."""
    med = np.median(resid)
    mad = mad_sd(resid, med)
    if mad == 0:
        return np.zeros(resid.shape, dtype=bool)
    return np.abs(resid - med) > k * mad


def quality_figures(m_cal: np.ndarray, field: float, condition: float) -> dict:
    r = norm_residuals(m_cal, field)
    out = outlier_mask(r)
    inl = ~out
    rms_in = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
    return {
        "residual_rms": rms_in,                              # |m_cal| - F over the inliers, input units
        "residual_rms_all": float(np.sqrt(np.mean(r ** 2))),
        "norm_spread": float(np.std(np.linalg.norm(m_cal, axis=1)) / field),   # relative, all samples
        "norm_spread_inliers": float(np.std(np.linalg.norm(m_cal[inl], axis=1)) / field) if inl.any() else float("nan"),
        "coverage": sphere_coverage(m_cal),
        "outlier_fraction": float(out.mean()),
        "condition": float(condition),
    }
