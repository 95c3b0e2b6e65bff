"""The ellipsoid (magnetometer) model of the MKC paper's appendix, eqs. (36)-(41), and its
conversion to the calibration convention of the recording spec: m_cal = S (m_raw - b),
S symmetric positive definite, |m_cal| ~ F.

Conditioning: raw magnetometer counts of +-500..6000 make the 9 quadratic features span
~8 orders of magnitude. We fit in normalised coordinates m' = (m - c0) / s0 (c0 the
per-axis median, s0 the median distance to it), where every feature is O(1), and map back
exactly: if (m' - r0')^T M' (m' - r0') = 1, then b = c0 + s0 r0' and M = M' / s0^2.
Normalising also keeps the origin inside the ellipsoid, which the "= 1" form of eq. (36)
requires (an ellipsoid through the origin has no such form).

S is taken as F * M^(1/2) with the symmetric square root built from a cyclic Jacobi
eigen-decomposition (calib/portable.py; bit-reproducible, as the C port's): Q diag(sqrt l) Q^T is
the same matrix whatever sign or order the eigenvectors have, so S can be neither mirrored nor
rotated (the defect of building S from Q alone). det(S) = 1 and F = det(M)^(-1/6)
is the geometric-mean radius, so S only reshapes and F carries the field strength.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .._validation import MKCInputError
from ..jsonout import jsonable
from ..robust import mad_sd
from .portable import jacobi_eigen, lstsq_sphere, solve3

#: Fewest samples for which a 9-parameter fit is even determined; real fits want hundreds.
MIN_SAMPLES = 10


class EllipsoidError(MKCInputError):
    """The data cannot give an ellipsoid (too few points, planar or linear data, indefinite fit)."""


def design_matrix(mag: np.ndarray) -> np.ndarray:
    """X_ell,k = [x^2, y^2, z^2, xy, xz, yz, x, y, z] for every row of mag (N, 3), eq. (36)-(37)."""
    x, y, z = mag[:, 0], mag[:, 1], mag[:, 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z], axis=1)


def quadric_from_theta(theta: np.ndarray):
    """A (3x3 symmetric) and B (3) of a1 x^2 + ... + a9 z = 1 (the matrices under eq. (37))."""
    a = np.asarray(theta, dtype=np.float64)
    A = np.array([[a[0], a[3] / 2, a[4] / 2],
                  [a[3] / 2, a[1], a[5] / 2],
                  [a[4] / 2, a[5] / 2, a[2]]])
    B = a[6:9].copy()
    return A, B


@dataclass(frozen=True)
class EllipsoidGeometry:
    centre: np.ndarray        # r0 of eq. (38)
    M: np.ndarray             # shape matrix: (m - r0)^T M (m - r0) = 1  (the paper's A_1)
    semi_axes: np.ndarray     # Sigma^(-1/2) of eq. (39), ascending eigenvalue order of M
    rotation: np.ndarray      # Q of eq. (39)-(40), a proper rotation (det +1)

    def surface(self, n_theta=24, n_phi=48):
        """Points on the ellipsoid via the parametrisation (40)-(41): r = r0 + Q Sigma^(-1/2) p."""
        th = np.linspace(-np.pi / 2, np.pi / 2, n_theta)
        ph = np.linspace(0, 2 * np.pi, n_phi)
        T, P = np.meshgrid(th, ph, indexing="ij")
        p = np.stack([np.cos(T) * np.cos(P), np.cos(T) * np.sin(P), np.sin(T)], axis=-1)
        return self.centre + (p * self.semi_axes) @ self.rotation.T


def geometry_from_theta(theta: np.ndarray) -> EllipsoidGeometry:
    """Centre (38), shape matrix A_1 = A / (1 + r0^T A r0), semi-axes and rotation (39)."""
    A, B = quadric_from_theta(theta)
    if not np.all(np.isfinite(A)) or not np.all(np.isfinite(B)):
        raise EllipsoidError("ellipsoid parameters are not finite")
    Al = A.tolist()
    eigA, _ = jacobi_eigen([row[:] for row in Al], False)
    if eigA[0] * eigA[-1] <= 0:
        raise EllipsoidError(
            f"the fitted quadric is not an ellipsoid: A is indefinite or singular (eigenvalues {eigA}); "
            "the data do not cover enough orientations, or the disturbances dominate")
    sol = solve3(Al, B.tolist())
    if sol is None:
        raise np.linalg.LinAlgError("Singular matrix")
    r0 = [-0.5 * v for v in sol]
    Ar0 = [r0[0] * Al[0][j] + r0[1] * Al[1][j] + r0[2] * Al[2][j] for j in range(3)]
    k = 1.0 + (Ar0[0] * r0[0] + Ar0[1] * r0[1] + Ar0[2] * r0[2])
    M = [[Al[i][j] / k for j in range(3)] for i in range(3)]
    lam, Q = jacobi_eigen([row[:] for row in M], True)
    if not lam[0] > 0:
        raise EllipsoidError(f"the fitted quadric is an empty or imaginary ellipsoid (1 + r0'A r0 = {k:.3g})")
    Q = np.array(Q)
    if np.linalg.det(Q) < 0:       # a proper rotation for (40); M itself does not depend on this
        Q[:, 0] = -Q[:, 0]
    return EllipsoidGeometry(centre=np.array(r0), M=np.array(M), semi_axes=1.0 / np.sqrt(np.array(lam)), rotation=Q)


def calibration_from_geometry(geom: EllipsoidGeometry):
    """(b, S, F) with m_cal = S (m - b), S symmetric positive definite with det(S) = 1."""
    lam, Q = jacobi_eigen(np.asarray(geom.M, dtype=np.float64).tolist(), True)
    F = (lam[0] * lam[1] * lam[2]) ** (-1.0 / 6.0)
    P = [[F * (Q[i][k] * math.sqrt(lam[k])) for k in range(3)] for i in range(3)]
    S = [[P[i][0] * Q[j][0] + P[i][1] * Q[j][1] + P[i][2] * Q[j][2] for j in range(3)] for i in range(3)]
    for i in range(3):
        for j in range(i + 1, 3):
            S[i][j] = S[j][i] = 0.5 * (S[i][j] + S[j][i])
    return geom.centre.copy(), np.array(S), float(F)


#: Gross outliers: samples farther from the coordinate-wise median than GROSS_FACTOR times the
#: GROSS_QUANTILE of all samples' distances to it. A hand-rotated recording spans at most ~1.5x
#: that quantile (even one that is still for 70% of its samples); a glitched read (a shorted bus,
#: a saturated axis decoded as 1e6 uT) lies thousands of times beyond. The quantile, not the median,
#: sets the scale so that a mostly still recording keeps its rotation; up to 5% gross samples are
#: recognised. Below 50x the correntropy fit down-weights them itself (measured: no change up to
#: ~600x the field); beyond ~2000x they fix the truncation bound a, and with it the floor of d,
#: so far out that the bursts' weights go flat (1-3 uT hard-iron error from one spike).
GROSS_QUANTILE = 0.95
GROSS_FACTOR = 50.0
#: The planarity check looks at the samples within GEOMETRY_CORE times that quantile, so that a
#: few off-plane spikes cannot make planar data look three-dimensional.
GEOMETRY_CORE = 3.0


def _distance_scale(mag: np.ndarray):
    with np.errstate(over="ignore", invalid="ignore"):     # a 1e300 read: its distance is inf, and gross
        r = np.linalg.norm(mag - np.median(mag, axis=0), axis=1)
    return r, float(np.quantile(r, GROSS_QUANTILE))


def gross_outlier_mask(mag: np.ndarray) -> np.ndarray:
    """True for the samples no magnetometer field explains (see GROSS_FACTOR); all False when the
    samples have no spread."""
    r, q = _distance_scale(mag)
    if not q > 0:
        return np.zeros(mag.shape[0], dtype=bool)
    return r > GROSS_FACTOR * q


def check_geometry_of_samples(mag: np.ndarray) -> None:
    """Refuse samples that cannot determine an ellipsoid, with the reason.

    The singular values are those of the samples within GEOMETRY_CORE distance quantiles of the
    median (all of a real recording), so neither a gross spike (it made sv[0] ~ its size: "a
    line") nor a few off-plane ones (they made a plane look solid) decide the verdict.
    """
    N = mag.shape[0]
    if N < MIN_SAMPLES:
        raise EllipsoidError(f"too few samples for an ellipsoid fit: {N} < {MIN_SAMPLES} (hundreds recommended)")
    r, q = _distance_scale(mag)
    core = r <= GEOMETRY_CORE * q
    C = mag[core] - np.median(mag, axis=0) if q > 0 and core.sum() >= MIN_SAMPLES else mag - np.median(mag, axis=0)
    sv = np.linalg.svd(C, compute_uv=False)
    if sv[0] == 0:
        raise EllipsoidError("all samples are identical: the sensor never moved")
    if sv[2] < 1e-3 * sv[0]:
        kind = "a line" if sv[1] < 1e-3 * sv[0] else "a plane"
        raise EllipsoidError(
            f"the samples lie on {kind} (singular values {np.round(sv, 6).tolist()}): rotate the sensor "
            "through all three axes, not about one axis only")


def sphere_fit(mag: np.ndarray):
    """Least-squares sphere |m - b|^2 = F^2 as the linear problem |m|^2 = 2 b^T m + k, k = F^2 - |b|^2.

    Well-posed wherever the origin lies (unlike the "= 1" ellipsoid form), hence the embedded
    peers' first step. Returns (b, F), or None when the fit is not a sphere (F^2 <= 0).
    """
    # the mean about the first sample: raw counts sit far from the origin (6000 counts around a
    # radius of 75), and a float build summing them directly loses ~0.1 count in the centre, which
    # moves the features' normalisation and hence the direction cells that decide what the window keeps
    ref = mag[0]
    c = ref + (mag - ref).mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((mag - c) ** 2, axis=1)))) or 1.0
    m = (mag - c) / scale
    sol = lstsq_sphere(m)        # the columns [2 m, 1] against |m|^2, reproducibly (calib/portable.py)
    if sol is None:
        return None
    b, k = np.array(sol[:3]), sol[3]
    F2 = k + (b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    if not (np.isfinite(F2) and F2 > 0):
        return None
    return c + scale * b, scale * float(np.sqrt(F2))


def robust_sphere_fit(mag: np.ndarray, passes: int = 2, k: float = 3.0):
    """sphere_fit, then refit without samples whose |m - b| - F exceeds k robust scales (bursts).

    The first fit already leaves out samples whose distance to the coordinate-wise median is more
    than k robust scales from the median distance: one spike at 20x the field drags a plain
    least-squares sphere so far that the trimming passes would keep the spikes and cut the sphere.
    """
    c = np.median(mag, axis=0)
    rad = np.linalg.norm(mag - c, axis=1)
    med = np.median(rad)
    mad = mad_sd(rad, med)
    first = np.abs(rad - med) <= k * mad if mad > 0 else None
    fit = sphere_fit(mag[first]) if first is not None and first.sum() >= 8 else sphere_fit(mag)
    for _ in range(passes):
        if fit is None:
            return None
        r = np.linalg.norm(mag - fit[0], axis=1) - fit[1]
        mad = mad_sd(r)
        keep = np.abs(r - np.median(r)) <= k * mad if mad > 0 else np.ones(len(r), bool)
        if keep.sum() < 8 or keep.all():
            return fit
        fit = sphere_fit(mag[keep])
    return fit


def sphere_theta(centre, radius):
    """theta of eq. (36)-(37) for the sphere |m - centre| = radius (in the features' coordinates).

    |m|^2 - 2 centre^T m = k with k = radius^2 - |centre|^2, divided by k so the target is 1; None
    when k <= 0 (the origin is not inside the sphere, so the "= 1" form cannot describe it).
    """
    c = [float(v) for v in centre]
    r = float(radius)
    k = r * r - (c[0] * c[0] + c[1] * c[1] + c[2] * c[2])     # spelt out: the C port's order
    if not (np.isfinite(k) and k > 0):
        return None
    return np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, -2.0 * c[0], -2.0 * c[1], -2.0 * c[2]]) / k


@dataclass
class Normalisation:
    offset: np.ndarray
    scale: float

    def apply(self, mag):
        return (mag - self.offset) / self.scale


def normalisation_for(mag: np.ndarray) -> Normalisation:
    c0 = np.median(mag, axis=0)
    s0 = float(np.median(np.linalg.norm(mag - c0, axis=1)))
    if not s0 > 0:
        raise EllipsoidError("samples have no spread around their median")
    return Normalisation(c0, s0)


def raw_geometry(geom_n: EllipsoidGeometry, norm: Normalisation) -> EllipsoidGeometry:
    """Map a geometry fitted in normalised coordinates back to raw sensor units."""
    return EllipsoidGeometry(centre=norm.offset + norm.scale * geom_n.centre, M=geom_n.M / norm.scale ** 2,
                             semi_axes=geom_n.semi_axes * norm.scale, rotation=geom_n.rotation)


@dataclass
class EllipsoidFit:
    """Result of fit_ellipsoid. apply(raw) gives calibrated samples m_cal = S (m - b)."""

    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field: float
    weights: np.ndarray
    quality: dict
    method: str
    geometry: EllipsoidGeometry
    theta_normalised: np.ndarray
    normalisation: Normalisation
    channels: list = field(default_factory=list)     # [{"sigma": s, "d": d}] for MKC methods
    estimator: object = None
    #: {"hard_iron_sd": [3], "heading_sd_deg"} when computed (calib/confidence.py), else None
    uncertainty: dict | None = None

    def apply(self, raw):
        raw = np.asarray(raw, dtype=np.float64)
        return (raw - self.hard_iron) @ self.soft_iron.T

    def calibration(self, unit: str = "uT", rules=None, raw=None):
        """This fit as the package's Calibration (calib/result.py), accepted or rejected by the
        acceptance predicate (calib/acceptance.py) for `unit`; with `raw` (the samples it was fitted
        to) its uncertainty is computed when not already known (calib/confidence.py)."""
        from .acceptance import AcceptanceRules, evaluate
        from .result import Calibration

        if raw is not None and self.uncertainty is None:
            from .confidence import calibration_uncertainty

            self.uncertainty = calibration_uncertainty(raw, self.hard_iron, self.soft_iron, self.field)
        rejection = evaluate(self.quality, self.field, unit, rules or AcceptanceRules())
        return Calibration(self.hard_iron, self.soft_iron, self.field, self.quality, rejection is None, rejection,
                           method=self.method, channels=list(self.channels), uncertainty=self.uncertainty,
                           samples_seen=int(len(self.weights)))

    def to_json(self, counts=None, status="accepted", reason=None):
        """The `calibrate` object of docs/spec/machine-output.md."""
        out = {
            "hard_iron": [float(v) for v in self.hard_iron],
            "soft_iron": [[float(v) for v in row] for row in self.soft_iron],
            "field": float(self.field),
            "channels": [{"sigma": jsonable(c.get("sigma")), "d": jsonable(c.get("d"))} for c in self.channels],
            "quality": jsonable(self.quality),
            "status": status,
            "reason": reason,
            "counts": counts,
            "method": self.method,
            "uncertainty": jsonable(self.uncertainty),
        }
        return out

