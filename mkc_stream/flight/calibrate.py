"""fit_flight: the attitude-aided calibration of a recording read from a flight or robot log.

Takes a Recording with the magnetometer, the attitude (aux qw, qx, qy, qz: body -> NED) and, when
present, the position (lat, lon in degrees, alt in m), current (A) and throttle (0..1); finds the
Earth field (WMM2025 at the median position, or a given field, or a unit field with the inclination
estimated), fits the vector model of vector_fit.py and returns a FlightCalibration in the package's
conventions: m_cal = S (m_raw - b - K c(t - delay)), S symmetric with det S = 1, field F in the
sensor's unit; plus the misalignment rotation and the physical scale (sensor unit per uT).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._validation import MKCInputError
from .delay import DELAY_DETERMINED, delay_standard_error
from .vector_fit import COVARIANCE_BLOCK_S, VectorFit, VectorFitSettings, fit_vector

QUAT = ("qw", "qx", "qy", "qz")
#: A fitted field strength this far from the model's (relative) is flagged: in a flight log in uT
#: the sensor gain is known to a few percent, so 10% means a wrong unit, a wrong field reference or a
#: calibration that absorbed an unmodelled disturbance.
FIELD_TOLERANCE = 0.10
#: A fitted yaw error of the attitude beyond this RMS (deg; twice the yaw_error prior's 5 deg) is not the
#: wandering error the first-order model holds: the log's heading and the magnetometer disagree more than
#: that model can carry (a heading offset of several degrees under strong manoeuvres, a wrong declination),
#: and the fit ran away along it (measured: 23 deg RMS and residuals of 7.5 uT on a flight whose logged yaw
#: was turned by 4 deg; 0.7-0.9 deg where it fits).
YAW_ERROR_LIMIT_DEG = 10.0


@dataclass
class FlightCalibration:
    hard_iron: np.ndarray              # b (3,), sensor unit
    soft_iron: np.ndarray              # S (3, 3) symmetric, det 1
    field: float                       # |S (m - b)| expected, sensor unit
    scale: float                       # sensor unit per uT (1 for a log in uT), nan without a field model
    misalignment_deg: np.ndarray       # rotation vector (deg) from the magnetometer to the attitude frame
    current: np.ndarray | None         # (3,) sensor unit per A
    throttle: np.ndarray | None        # (3,) sensor unit per unit throttle
    delay_s: float | None
    current_ci: np.ndarray | None      # (3, 2) 95% interval, cluster-robust (see vector_fit)
    earth: object | None               # earthfield.EarthField or None
    held: list
    observable: dict
    vif: dict
    unit: str
    samples: int
    skipped: int                       # rows without a finite attitude / signal, left out
    fit: VectorFit
    notes: list
    delay_ci_s: tuple | None = None    # 95% interval of the searched delay (delay_standard_error), None if not

    @property
    def yaw_error_rms_deg(self) -> float | None:
        """RMS of the attitude's fitted yaw error (deg), None without the yaw-error term."""
        y = self.fit.yaw_error_deg
        return None if y is None or y.size == 0 else float(np.sqrt(np.mean(y * y)))

    def to_json(self) -> dict:
        """compensation and earth_field of docs/spec/machine-output.md, with the calibration's fields."""
        def lst(x):
            return None if x is None else [float(v) for v in np.ravel(x)]
        comp = None
        if self.current is not None or self.throttle is not None:
            comp = {"current": lst(self.current), "current_unit": f"{self.unit}/A", "throttle": lst(self.throttle),
                    "delay_s": None if self.delay_s is None else float(self.delay_s),
                    "current_ci": None if self.current_ci is None else [[float(a), float(b)] for a, b in self.current_ci]}
        return {"hard_iron": lst(self.hard_iron), "soft_iron": [lst(r) for r in self.soft_iron], "field": float(self.field),
                "channels": [{"sigma": float(s), "d": float(d)} for s, d in zip(self.fit.sigma, self.fit.d)
                             if math.isfinite(s)],
                "compensation": comp, "earth_field": None if self.earth is None else self.earth.to_json(),
                "attitude_fit": {"scale_per_uT": None if not math.isfinite(self.scale) else float(self.scale),
                                 "misalignment_deg": lst(self.misalignment_deg), "held": list(self.held),
                                 "tilt_error_sd_deg": self.fit.tilt_sd_deg,
                                 "yaw_error_rms_deg": self.yaw_error_rms_deg,
                                 "tilt_error_sd_estimated_deg": self.fit.tilt_sd_estimated,
                                 "observable": dict(self.observable), "vif": {k: float(v) for k, v in self.vif.items()},
                                 "samples": int(self.samples), "skipped": int(self.skipped), "notes": list(self.notes)}}


def _rotvec_deg(Q) -> np.ndarray:
    """Rotation vector (deg) of a rotation matrix."""
    c = max(-1.0, min(1.0, (np.trace(Q) - 1.0) / 2.0))
    ang = math.acos(c)
    if ang < 1e-12:
        return np.zeros(3)
    v = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]]) / (2.0 * math.sin(ang))
    return np.degrees(ang) * v


def package_form(A, h_norm):
    """(S det 1, field in sensor unit, scale per field unit, misalignment rotation vector deg) of A:
    A^-1 = Q P (P symmetric positive definite: the sensor-frame soft iron and gain; Q a rotation)."""
    U, sv, Vt = np.linalg.svd(np.linalg.inv(A))
    if np.linalg.det(U @ Vt) < 0:
        raise MKCInputError("the fitted vector model mirrors the field (an axis has the wrong sign)")
    P = (Vt.T * sv) @ Vt
    Q = U @ Vt
    k = float(np.prod(sv) ** (1.0 / 3.0))           # field unit per sensor unit
    return 0.5 * (P + P.T) / k, h_norm / k, 1.0 / k, _rotvec_deg(Q)


def _median_position(rec):
    if not all(c in rec.aux for c in ("lat", "lon")):
        return None
    lat, lon = rec.aux["lat"], rec.aux["lon"]
    alt = rec.aux.get("alt", np.zeros_like(lat))
    ok = np.isfinite(lat) & np.isfinite(lon) & ~((lat == 0) & (lon == 0))      # (0, 0): no GPS fix
    if ok.sum() < 10:
        return None
    a = alt[ok][np.isfinite(alt[ok])]
    return float(np.median(lat[ok])), float(np.median(lon[ok])), float(np.median(a)) if a.size else 0.0


def throttle_free(names, f) -> bool:
    """True when the current is the only power signal fitted (its interval then decides the delay)."""
    return not any(n != "current" and f"K[{n}]=0" not in f.held for n in names)


def require_attitude(rec, what: str) -> None:
    """MKCInputError unless the recording has the attitude quaternion columns."""
    missing = [c for c in QUAT if c not in rec.aux]
    if missing:
        raise MKCInputError(f"the recording has no attitude (missing {', '.join(missing)}); the attitude-aided "
                            f"{what} needs qw, qx, qy, qz (body -> NED)")


def earth_reference(rec, earth, lat, lon, alt, date, notes: list):
    """(EarthField or None, h_NED in uT or None): the field reference given (an EarthField or an NED
    vector), else WMM2025 at --lat/--lon or the recording's median GPS position on `date` (the
    recording's own date when not given; today's, with a note, when it has none); (None, None) when
    there is neither a reference nor a position."""
    if earth is not None:
        if hasattr(earth, "ned_uT"):
            return earth, np.asarray(earth.ned_uT, dtype=np.float64)
        return None, np.asarray(earth, dtype=np.float64).reshape(3)
    pos = (float(lat), float(lon), float(alt)) if lat is not None and lon is not None else _median_position(rec)
    if pos is None:
        return None, None
    from .earthfield import earth_field

    if date is None:
        date = rec.meta.get("date") or rec.meta.get("start_time")
        if date is None:
            notes.append("no date in the recording: the Earth field is for today's date")
    ef = earth_field(*pos, date=date)
    return ef, ef.ned_uT


def fit_flight(rec, *, earth=None, lat=None, lon=None, alt=0.0, date=None, power=None,
               robust=True, yaw_only=False, delay=None, max_delay=0.5, max_vif=None,
               tilt_sd_deg="auto") -> FlightCalibration:
    """Attitude-aided calibration of ``rec`` (module doc).

    earth: an earthfield.EarthField or an NED vector in uT (overrides the position); lat/lon/alt
    (deg, deg, m): the position when the log has none; date: for WMM2025 (decimal year, date or ISO;
    the recording's meta "date" or "start_time" when given there, else today, noted). power: aux
    columns used as power signals when present (None: the current when present, else the
    throttle; both are usually nearly collinear, current = f(throttle)). delay: a fixed delay (s) instead of the
    search over [-max_delay, max_delay] (negative: the logged signal is the late one, vector_fit's module doc).
    max_vif: observability threshold (vector_fit.MAX_VIF). tilt_sd_deg: the attitude's roll/pitch error
    (deg, 1 sd), corrected for in the fit (vector_fit's module doc): a stated value, "auto" (estimated
    from the fit's residuals, tilt_error.py) or None (not corrected)."""
    from .vector_fit import MAX_VIF

    notes = []
    require_attitude(rec, "fit")
    q = np.stack([rec.aux[c] for c in QUAT], axis=1)
    if power is None:          # the current when the log has it, else the throttle (module doc)
        power = ("current",) if "current" in rec.aux else ("throttle",)
    names = [p for p in power if p in rec.aux]
    c = np.stack([rec.aux[p] for p in names], axis=1) if names else np.zeros((rec.t.shape[0], 0))
    ok = np.isfinite(rec.mag).all(axis=1) & np.isfinite(q).all(axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    ok &= np.isfinite(c).all(axis=1) & np.isfinite(rec.t)
    skipped = int((~ok).sum())
    if skipped:
        notes.append(f"{skipped} rows without a finite attitude, field or power signal were left out")
    ef, h = earth_reference(rec, earth, lat, lon, alt, date, notes)
    if h is None:
        notes.append("no position and no field reference: a unit field with the inclination estimated; "
                     "the scale to uT is unknown")
    s = VectorFitSettings(robust=robust, yaw_only=yaw_only, max_delay=max_delay, delay=delay,
                          max_vif=MAX_VIF if max_vif is None else max_vif, tilt_sd_deg=tilt_sd_deg)
    f = fit_vector(rec.t[ok], rec.mag[ok], q[ok], h, c[ok], tuple(names), s)
    S, field, scale, mis = package_form(f.A, float(np.linalg.norm(f.h_ned)))
    if h is None:
        scale = math.nan
    unit = rec.meta.get("units.mag", "uT")
    cur = thr = ci = None
    nx = 4 + len(names)
    for j, n in enumerate(names):
        if f"K[{n}]=0" in f.held:
            continue
        if n == "current":
            cur = f.K[:, j].copy()
            sd = np.array([f.theta_sd(i, 4 + j) for i in range(3)])
            ci = np.stack([cur - 1.96 * sd, cur + 1.96 * sd], axis=1) if f.cov is not None else None
        elif n == "throttle":
            thr = f.K[:, j].copy()
    del nx
    delay_s = f.delay_s
    if delay_s is not None and ci is not None and throttle_free(names, f) and np.all((ci[:, 0] <= 0) & (ci[:, 1] >= 0)):
        delay_s = None
        notes.append("no current coefficient differs from 0 at 95%: the delay is not determined and not reported")
    elif delay_s is not None and max_delay and delay is None and abs(delay_s) >= 0.99 * max_delay:
        delay_s = None
        notes.append(f"the delay ran to the end of the search (+-{max_delay * 1e3:g} ms): not determined by this log "
                     "(a weak or slow current signal), not reported")
    delay_ci = None
    if delay_s is not None and delay is None and max_delay:
        half = 1.96 * delay_standard_error(rec.t[ok], c[ok], f, COVARIANCE_BLOCK_S)
        delay_ci = (delay_s - half, delay_s + half)
        if not half <= DELAY_DETERMINED:
            notes.append(f"the delay's 95% interval is +-{half * 1e3:.0f} ms about {delay_s * 1e3:.0f} ms (the power "
                         f"signal moves too slowly to time it): not determined, not reported")
            delay_s = delay_ci = None
    if "A02=A20" in f.held and "A22=(A00+A11)/2" not in f.held:
        notes.append(f"the responses of x and y to the vertical field held symmetric (A02=A20, A12=A21): the "
                     f"flight tilts little (VIF of h_z {f.vif['h_z']:.3g}); a tilt misalignment of the sensor goes "
                     "into the hard iron's x and y, which leaves the level heading unchanged")
    if yaw_only or "A22=(A00+A11)/2" in f.held:
        notes.append("vertical soft iron held at its prior (A02=A20, A12=A21, A22=(A00+A11)/2): "
                     + ("yaw-only mode" if yaw_only else f"the flight does not tilt enough (VIF of h_z "
                                                        f"{f.vif['h_z']:.3g})")
                     + "; the hard iron's z carries the vertical gain's error times the vertical field")
    if f.tilt_sd_estimated is not None:
        notes.append(f"the attitude's roll/pitch error, estimated from the residuals: {f.tilt_sd_estimated:.2f} deg; "
                     + ("the fit is corrected for it" if f.tilt_sd_deg else "no correction applied (none seen, or "
                        "larger than the flight's tilt variation can carry)"))
    y = f.yaw_error_deg
    if y is not None and y.size and float(np.sqrt(np.mean(y * y))) > YAW_ERROR_LIMIT_DEG:
        notes.append(f"the attitude's fitted yaw error is {float(np.sqrt(np.mean(y * y))):.1f} deg RMS, more than the "
                     f"{YAW_ERROR_LIMIT_DEG:g} deg its model holds: the log's heading and the magnetometer disagree "
                     "beyond a wandering error (a heading offset of the attitude, a wrong declination); not reliable")
    if ef is not None and math.isfinite(scale) and unit == "uT" and abs(scale - 1.0) > FIELD_TOLERANCE:
        notes.append(f"the fitted gain is {scale:.3f} sensor uT per model uT (more than {FIELD_TOLERANCE:.0%} from 1): "
                     "check the unit, the position/date, or local disturbances")
    return FlightCalibration(hard_iron=f.b, soft_iron=S, field=field, scale=scale, misalignment_deg=mis,
                             current=cur, throttle=thr, delay_s=delay_s, current_ci=ci, earth=ef, held=f.held,
                             observable=f.observable, vif=f.vif, unit=unit, samples=int(ok.sum()), skipped=skipped,
                             fit=f, notes=notes, delay_ci_s=delay_ci)
