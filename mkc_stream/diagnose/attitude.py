"""The attitude-aided part of the diagnosis: a vector baseline from the log's attitude, and the effects of
the logged aux signals tested on its three-channel residual.

A flight covers too little of the sphere for the ellipsoid baseline (the calibrator rejects it), but a
log with the attitude (aux qw, qx, qy, qz, body -> NED) holds the field's direction at every sample. The
baseline is then the flight calibration without power terms (flight.fit_flight with power=(): it knows
no current), against the Earth field from WMM2025 at the log's GPS position (or a given field; without
either, a unit field with the inclination estimated, the residual in the sensor's unit):
    r_k = m_k - (A R(q_k)^T h_E + b) - dpsi(t_k) g_k,
the last term the attitude's slowly wandering yaw error (flight/yaw_error.py), kept in the baseline
because it is the attitude's error, not the sensor's (without it a 3 deg yaw error leaves a ~1 uT
residual over tens of seconds, which hides a current effect of the same size). On r the effects of
the library that are functions of logged columns are tested (attitude_effects.py): current_hard_iron,
throttle_hard_iron, temperature_offset. An effect is *found* when its test over the three channels (a
time-shift test of its Wald statistic) is significant at LEVEL and it lowers the held-out residual (the
share of the held-out residual's sum of squares it removes is above 0). Measured against simulated
flights with known K: tools/study_attitude_diagnosis.py.

The baseline is not usable (and nothing is tested, with the reason) when fit_flight cannot fit it (the
flight does not turn enough for the horizontal field) or when `calibrate --attitude` would reject it
(a fitted gain more than SCALE_TOLERANCE from the model's field, for a log in uT). Rows without a finite
attitude are left out and counted. The rows are the diagnosis frame's (its decimation and time blocks).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..jsonout import jsonable

QUAT = ("qw", "qx", "qy", "qz")
#: the rejection bar of `calibrate --attitude` (commands/flightcal.py): a fitted gain (sensor uT per
#: model uT) further than this from 1 means a wrong unit, position or date, or a disturbance
SCALE_TOLERANCE = 0.15
#: significance level of each effect's test (three effects: family-wise at most 3%)
LEVEL = 0.01
#: the effects of the library that are functions of logged aux columns, in the order tested
EFFECT_NAMES = ("current_hard_iron", "throttle_hard_iron", "temperature_offset")
SIGNIFICANCE = ("circular time-shift test of the cluster-robust Wald statistic of the effect's coefficients over "
                "the three channels (the aux column shifted 10-90% of the recording against the residual; keeps "
                "both autocorrelations); 95% intervals cluster-robust over the training blocks, t(G-1)")
#: a found effect that adds less than this share of the held-out variance given the other found effects is
#: reported as not told apart from them (the current and the throttle of a multirotor move together: on
#: log171 their correlation is 0.94). Lenient on purpose: the held-out share of a null current term on the
#: null flights of tools/study_attitude_diagnosis.py spread over -0.05..0.08, so only a gain next to nothing
#: is called ambiguous
AMBIGUOUS_GAIN = 0.01
#: a size this many times the library's realistic upper bound (its Params' high) is noted as implausible
IMPLAUSIBLE_FACTOR = 10.0
HELD_OUT_RULE = ("found = significant at the level AND the held-out residual's sum of squares falls "
                 "(variance_explained > 0 on the held-out blocks, intercept-only against intercept + effect, "
                 "both fitted on the training blocks)")


@dataclass
class AttitudeDiagnosis:
    ran: bool                           # the baseline was fitted and usable, the effects were tested
    reason: str | None                  # why not (no attitude, the fit's or the calibrator's reason)
    baseline: dict | None               # the attitude baseline's figures (None without attitude)
    tests: list = field(default_factory=list)     # attitude_effects.EffectTest
    ambiguous: dict = field(default_factory=dict)  # found effect -> the found effects it cannot be told from
    seconds: float = 0.0

    @property
    def found(self) -> list:
        return [e.name for e in self.tests if e.found]

    def test(self, name):
        return next((e for e in self.tests if e.name == name), None)

    def to_json(self) -> dict:
        return jsonable({"ran": self.ran, "reason": self.reason, "baseline": self.baseline,
                         "level": LEVEL, "significance": SIGNIFICANCE, "rule": HELD_OUT_RULE,
                         "effects": [e.to_json() for e in self.tests], "found": self.found,
                         "ambiguous_with": self.ambiguous, "seconds": self.seconds})


def _skipped(reason, baseline=None, t0=None) -> AttitudeDiagnosis:
    return AttitudeDiagnosis(False, reason, baseline, seconds=0.0 if t0 is None else time.perf_counter() - t0)


def _rows(rec, frame):
    """(row indices of rec, time block of each, training mask, duration s): the frame's when given."""
    from .frame import N_BLOCKS

    if frame is not None:
        idx = np.arange(0, len(rec), frame.decimation)
        if idx.size == frame.n:
            return idx, frame.block, frame.train, frame.duration
    idx = np.arange(len(rec))
    t = rec.t
    dur = float(t[-1] - t[0]) if t.size > 1 else 0.0
    block = np.minimum(((t - t[0]) / max(dur, 1e-300) * N_BLOCKS).astype(np.int64), N_BLOCKS - 1)
    return idx, block, block % 2 == 0, dur


def _field_json(fc, h_ned, given: bool) -> dict:
    """The field the baseline used: WMM2025 (at the given or the log's position), a given NED vector, or the
    unit field of fit_flight's mode without a reference."""
    if fc.earth is not None:
        return {**fc.earth.to_json(), "source": "given" if given else "the log's GPS position"}
    h = np.asarray(h_ned, dtype=np.float64)
    if not given:
        return {"model": "unit field", "inclination_deg": math.degrees(math.atan2(h[2], h[0])),
                "source": "no position and no field reference: a unit field with the inclination estimated; "
                          "the residual is in the sensor's unit, not uT"}
    return {"model": "given", "ned_uT": h.tolist(), "intensity": float(np.linalg.norm(h)), "source": "given"}


def fit_attitude_baseline(rec, ok, *, earth=None, lat=None, lon=None, alt=0.0, date=None):
    """(FlightCalibration or None, baseline dict, reason or None) of the attitude baseline on rec (the module
    doc); ok: the rows fit_flight will use (finite field, attitude and time)."""
    from .._validation import MKCInputError
    from ..flight import fit_flight

    bad_att = int((~ok).sum())
    base = {"samples": int(ok.sum()), "skipped": bad_att,
            "skipped_reason": "rows without a finite attitude (qw..qz), field or time" if bad_att else None}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)         # an iteration cap: the fit's notes say it
            # no tilt correction: the baseline leaves effects out on purpose, and its residuals would read them as
            # the attitude's tilt error (flight/tilt_error.py)
            fc = fit_flight(rec, earth=earth, lat=lat, lon=lon, alt=alt, date=date, power=(), tilt_sd_deg=None)
    except (MKCInputError, ValueError, np.linalg.LinAlgError) as exc:
        return None, {**base, "usable": False}, f"the attitude-aided fit failed: {exc}"
    r = fc.fit.residuals
    mad = np.median(np.abs(r - np.median(r, axis=0)), axis=0) * 1.4826
    given = earth is not None or lat is not None
    base.update({"usable": True, "field": _field_json(fc, fc.fit.h_ned, given), "unit": fc.unit,
                 "residual_rms": np.sqrt(np.mean(r * r, axis=0)).tolist(), "residual_robust_sd": mad.tolist(),
                 "hard_iron": fc.hard_iron.tolist(), "scale_per_uT": fc.scale if math.isfinite(fc.scale) else None,
                 "held": list(fc.held), "vif_h_z": fc.vif.get("h_z"), "converged": bool(fc.fit.converged),
                 "notes": list(fc.notes)})
    if fc.unit == "uT" and math.isfinite(fc.scale) and abs(fc.scale - 1.0) > SCALE_TOLERANCE:
        base["usable"] = False
        return fc, base, (f"the calibrator would reject it: fitted field {fc.scale:.3f} x the Earth-field model "
                          f"(more than {SCALE_TOLERANCE:.0%} from 1): wrong unit, position or date, or a disturbance "
                          "that does not move with the vehicle")
    return fc, base, None


def _projector(fc, t, q):
    """attitude_effects.BaselineProjector of the fitted baseline (its regressors, weights and yaw term)."""
    from ..flight.vector_fit import VectorFitSettings, body_field, rotation_matrices
    from ..flight.yaw_error import YawBasis, yaw_regressor
    from .attitude_effects import BaselineProjector

    f = fc.fit
    R = rotation_matrices(q)
    X = np.column_stack([body_field(R, f.h_ned), np.ones(t.shape[0])])
    C = f.weights / (np.asarray(f.d) ** 2)[None, :] if np.all(np.isfinite(f.sigma)) else np.ones_like(f.weights)
    s = VectorFitSettings()
    basis = YawBasis(t, s.yaw_knot_s, s.yaw_prior_deg) if f.yaw_error_deg is not None else None
    g = yaw_regressor(R, f.h_ned, f.A) if basis is not None else None
    return BaselineProjector(X, C, basis, g)


def _ambiguity(tests, r, train) -> dict:
    """For each found effect, the found effects given which it adds less than AMBIGUOUS_GAIN of the held-out
    variance: the held-out sum of squares of all found effects fitted jointly against all but that one."""
    from .attitude_effects import held_out_ss, robust_scales

    found = [e for e in tests if e.found]
    if len(found) < 2:
        return {}
    scale = robust_scales(r[train])
    n = r.shape[0]
    intercepts = np.zeros((n, 3, 3))
    intercepts[:, np.arange(3), np.arange(3)] = 1.0

    def ss(effects):
        return held_out_ss(r, train, np.concatenate([intercepts] + [e.columns for e in effects], axis=2), scale)

    full, none = ss(found), ss([])
    out = {}
    for e in found:
        rest = [x for x in found if x is not e]
        gain = ss(rest) - full
        e.held_out["adds_given_others"] = gain / none if none > 0 else None
        if not gain > AMBIGUOUS_GAIN * none:
            out[e.name] = [x.name for x in rest]
    return out


def _plausibility(tests) -> None:
    """A note on each size far above the library's realistic range (IMPLAUSIBLE_FACTOR x its Params' high)."""
    from ..sim.effects import EFFECTS

    for e in tests:
        if not e.testable or e.name not in EFFECTS or e.size.get("unit") not in ("uT/A", "uT", "nT/degC"):
            continue
        hi = max(p.high for p in EFFECTS[e.name].params[:3])
        big = max(abs(v) for v in e.size["value"])
        if big > IMPLAUSIBLE_FACTOR * hi:
            e.size["note"] = (f"{big:.3g} {e.size['unit']} is over {IMPLAUSIBLE_FACTOR:g} x the library's realistic "
                              f"upper bound ({hi:g} {e.size['unit']}): it may stand in for another slow effect "
                              "(a drift, or another aux signal that moves with it)")


def diagnose_attitude(rec, frame=None, *, earth=None, lat=None, lon=None, alt=0.0, date=None, level=LEVEL,
                      log=None) -> AttitudeDiagnosis:
    """The attitude-aided diagnosis of ``rec`` (module doc) on the rows and blocks of ``frame``
    (diagnose's Frame; None: every row, frame.N_BLOCKS blocks). earth/lat/lon/alt/date: as fit_flight's."""
    from ..io.recording import Recording
    from .attitude_effects import run_effect_test

    t0 = time.perf_counter()
    log = log or (lambda s: None)
    missing = [c for c in QUAT if c not in rec.aux]
    if missing:
        return _skipped(f"the recording has no attitude (missing {', '.join(missing)}): the attitude-aided "
                        "baseline needs qw, qx, qy, qz (body -> NED)", t0=t0)
    idx, block, train, duration = _rows(rec, frame)
    sub = Recording(t=rec.t[idx], mag=rec.mag[idx], aux={k: v[idx] for k, v in rec.aux.items()}, meta=dict(rec.meta))
    q = np.stack([sub.aux[c] for c in QUAT], axis=1)
    ok = (np.isfinite(sub.mag).all(axis=1) & np.isfinite(q).all(axis=1) & np.isfinite(sub.t)
          & (np.nan_to_num(np.linalg.norm(q, axis=1)) > 0.5))
    if ok.sum() < 100:
        return _skipped(f"only {int(ok.sum())} rows have a finite attitude (needs >= 100)",
                        {"usable": False, "samples": int(ok.sum()), "skipped": int((~ok).sum()),
                         "skipped_reason": "rows without a finite attitude (qw..qz), field or time"}, t0)
    fc, base, why = fit_attitude_baseline(sub, ok, earth=earth, lat=lat, lon=lon, alt=alt, date=date)
    if fc is not None and fc.samples != int(ok.sum()):       # fit_flight's own row rule must be the same
        why = why or f"the attitude fit used {fc.samples} rows, the diagnosis expected {int(ok.sum())}"
        base["usable"] = False
    if why is not None:
        log(f"attitude-aided baseline not usable: {why}")
        return _skipped(why, base, t0)
    unit = base["unit"] if base["field"]["model"] != "unit field" else f"{base['unit']} (unit-field scale)"
    log(f"attitude-aided baseline: residual RMS {', '.join(f'{v:.3g}' for v in base['residual_rms'])} {unit}, "
        f"{base['samples']} rows, {base['skipped']} skipped")
    r = fc.fit.residuals
    t = sub.t[ok]
    proj = _projector(fc, t, q[ok])
    aux = {k: v[ok] for k, v in sub.aux.items()}
    tests = [run_effect_test(n, aux, t, duration, r, train[ok], block[ok], proj, base["unit"], level)
             for n in EFFECT_NAMES]
    for e in tests:
        if e.testable:
            log(f"  {e.name}: p {e.p_value:.2g}, held-out variance explained {e.held_out['variance_explained']:.3f}"
                f" -> {'found' if e.found else 'not found'}")
    amb = _ambiguity(tests, r, train[ok])
    _plausibility(tests)
    return AttitudeDiagnosis(True, None, base, tests, amb, time.perf_counter() - t0)
