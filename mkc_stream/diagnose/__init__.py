"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, how far it
shrinks once that effect is added.

``diagnose(recording)`` fits the baseline (MKC-EM calibration, white noise, bursts, a regular
clock) to a :class:`~mkc_stream.io.recording.Recording`, replays the simulator on its own
timestamps, directions and aux signals many times, compares a fixed panel of statistics
(:mod:`.panel`) as calibrated z-scores summarised by a gap index (about 1 when the simulator
matches; :mod:`.gap`), runs one matched test per deterministic effect of the library (a small
slow effect the omnibus index cannot see; :mod:`.matched`; the latency's test also reads the
magnetometer's timing against the gyroscope, :mod:`.gyro_timing`), and attributes the gap to effects
of the library on held-out time blocks (:mod:`.attribution`), and calls an explanation complete
only if the residual no longer follows any recorded aux signal (:mod:`.completeness`; else
"partially explained", naming the signal). When the calibrator would not accept the baseline's
calibration, the verdict is "baseline_rejected", with the calibrator's reason, and only what does
not rest on the calibration is tested (:mod:`.scope`; its verdict is ``info.scope``'s
``verdict_on_testable``). The verdict is decided from figures returned beside it
(:mod:`.verdict`: "explained" only with the held-out gap index at or below its alarm level), and
the effects that were not tested are listed with the reason (``dropped``). A recording with the attitude
(aux qw, qx, qy, qz) also gets the attitude-aided part (:mod:`.attitude`): a vector baseline against the
Earth field and the effects of its logged aux signals tested on its three-channel residual, beside the
verdict (``attitude_aided``; the verdict itself reads the ellipsoid baseline). ``Diagnosis.to_json()`` is the
object of docs/spec/machine-output.md; :mod:`.report` writes the human report and plots.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..jsonout import finite_or_none, jsonable
from .frame import DiagnoseError

__all__ = ["DiagnoseError", "Diagnosis", "diagnose", "PROFILES"]

#: fast: the 60 s budget for 10^4 samples on 2 cores; full: more replicas, bootstraps, all samples.
PROFILES = {
    "fast": {"replicas": 40, "screen_replicas": 16, "boot": 40, "max_samples": 20000},
    "full": {"replicas": 100, "screen_replicas": 40, "boot": 200, "max_samples": None},
}


@dataclass
class Diagnosis:
    verdict: str
    gap_before: float
    gap_after: float
    threshold: float
    shrink: float
    where: list
    effects: list
    ambiguous_with: list
    selected: list
    excluded: list
    info: dict = field(default_factory=dict)
    basis: object = None                 # .verdict.Basis: the figures the verdict was decided from
    dropped: list = field(default_factory=list)   # [{"name", "reason"}]: effects not tested, and why
    attitude: object = None              # .attitude.AttitudeDiagnosis, None when not asked for
    engine: object = field(default=None, repr=False)
    evaluations: dict = field(default_factory=dict, repr=False)

    def to_json(self) -> dict:
        effects = []
        for r in self.effects:
            effects.append({
                "name": r.name, "testable": r.testable, "selected": r.selected, "status": r.status,
                "reason": r.reason, "shrink": finite_or_none(r.shrink) if r.testable else None,
                "shrink_ci": r.shrink_ci, "shrink_given_selected": finite_or_none(r.shrink_given_selected),
                "gap": finite_or_none(r.gap), "magnitude": jsonable(r.magnitude),
                "magnitude_ci": jsonable(r.magnitude_ci)})
        return {
            "verdict": self.verdict,
            "verdict_basis": None if self.basis is None else jsonable(self.basis.to_json()),
            "gap_before": finite_or_none(self.gap_before),
            "gap_after": finite_or_none(self.gap_after),
            "where": self.where,
            "effects": effects,
            "ambiguous_with": self.ambiguous_with,
            "selected": self.selected,
            "shrink": finite_or_none(self.shrink),
            "threshold": finite_or_none(self.threshold),
            "excluded": self.excluded,
            "dropped": self.dropped,
            "info": jsonable(self.info),
            "attitude_aided": None if self.attitude is None else self.attitude.to_json(),
        }


def _where(eng, ev, n=15):
    z = np.nan_to_num(ev.z)
    off = np.array([eng.gi.names[k] in eng.gi.off for k in eng.gi.idx], dtype=bool)
    z[off] = 0.0                # statistics the recording cannot test are no gap
    order = np.argsort(-np.abs(z))[:n]
    out = []
    for i in order:
        if off[i]:
            continue
        if abs(z[i]) < 3.0 and out:
            break
        fam, (channel, label) = eng.labels[i]
        out.append({"family": fam, "channel": channel, "bin": label, "z": float(z[i])})
    return out


def diagnose(recording, *, exclude=(), profile="fast", replicas=None, seed=0, max_samples="profile",
             log=None, attitude=True, earth=None, lat=None, lon=None, date=None) -> Diagnosis:
    """Diagnose the sim-to-real gap of a recording (see the module documentation).

    exclude: effect names to leave out of the library (the blind benchmark's "removed" trials);
    an effect whose form holds one of them as a special case (``MeanForm.contains``) goes too.
    profile: "fast" (the 60 s budget for 10^4 samples) or "full". log: a callable for progress lines.
    attitude: run the attitude-aided part (:mod:`.attitude`; skipped with the reason without an attitude);
    earth (an NED field in uT or a flight.EarthField), lat/lon (deg), date: its field reference when the log
    has no GPS position (else a unit field with the inclination estimated).
    Raises DiagnoseError for recordings that cannot be diagnosed, with the reason.
    """
    from ..sim.effects import EFFECTS
    from . import gap
    from .attribution import Attribution, effect_testable
    from .baseline import INCLINATION_CONVENTION, fit_baseline, inclination_deg
    from .completeness import aux_left
    from .engine import Candidate, Engine
    from .frame import prepare
    from .gyro_timing import gyro_delay
    from .matched import MatchedTests, mean_effects
    from .verdict import decide, held_out_rss_drop

    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; use {', '.join(PROFILES)}")
    cfg = dict(PROFILES[profile])
    if replicas is not None:
        cfg["replicas"] = int(replicas)
        cfg["screen_replicas"] = min(cfg["screen_replicas"], int(replicas))
    if max_samples != "profile":
        cfg["max_samples"] = max_samples
    unknown = sorted(set(exclude) - set(EFFECTS))
    if unknown:
        raise ValueError(f"unknown effect(s) to exclude: {', '.join(unknown)}")
    log = log or (lambda s: None)
    t_start = time.perf_counter()

    frame = prepare(recording, cfg["max_samples"])
    base = fit_baseline(frame)
    eng = Engine(frame, base, n_replicas=cfg["replicas"], seed=seed)
    scope = base.scope
    log(f"baseline: F {base.fit.state.F:.4g} {frame.unit}, noise {base.sigma[0]:.3g} {frame.unit}, "
        f"{frame.n} samples{'' if frame.decimation == 1 else f' (decimated by {frame.decimation})'}")
    if not scope.accepted:
        log(f"the calibrator rejects the baseline calibration ({scope.reason}): testing only {scope.tested()}")
    att_diag = None
    if attitude:
        from .attitude import diagnose_attitude

        att_diag = diagnose_attitude(recording, frame, earth=earth, lat=lat, lon=lon, date=date, log=log)
    ev0 = eng.evaluate(Candidate(), keep_raw=True)
    thr0 = gap.threshold(eng.calibrate(ev0))
    by_gap = bool(ev0.G > thr0)
    log(f"gap index {ev0.G:.3f} (held-out; no-gap level 1, alarm above {thr0:.3f})")

    # an effect whose form holds an excluded one as a special case would explain the excluded
    # one's evidence in its own shape: it is left out with it
    with_it = {n: [x for x in getattr(EFFECTS[n].form, "contains", ()) if x in set(exclude)]
               for n in EFFECTS if n not in set(exclude)}
    with_it = {n: xs for n, xs in with_it.items() if xs}
    library = [n for n in EFFECTS if n not in set(exclude) and n not in with_it]
    # the omnibus gap index misses small slow mean effects an oracle sees: one matched test per
    # testable mean effect of the library (Bonferroni; see .matched) can also raise the alarm
    # the magnetometer's timing against the gyroscope: the latency test's second view
    gyro = gyro_delay(frame, base.fit.state, base.valid[:, 0]) if frame.gyro is not None else None
    if gyro is not None and gyro["testable"]:
        log(f"timing against the gyroscope: magnetometer late by {gyro['delay_ms']:.2f} "
            f"+- {gyro['se_ms']:.2f} ms (t {gyro['t']:.1f})")
    mt = MatchedTests(eng, ev0, mean_effects([n for n in library if effect_testable(base, n)[0]]),
                      gyro=gyro)
    fired = mt.fired()
    by_matched = bool(fired) and not by_gap
    detected = by_gap or by_matched
    if fired:
        log(f"matched tests fired (level {mt.level:.2g} each): {', '.join(fired)}")
    ev0.rep_raw = None
    att = Attribution(eng, ev0, thr0, library, n_boot=cfg["boot"], seed=seed, screen_R=cfg["screen_replicas"], log=log,
                      matched=mt)
    results, selected, ambiguous, final = att.run(detected, by_matched=by_matched)
    first = results[selected[0]].shrink if selected else float("nan")
    ms = att.matched_summary
    detected_by = "gap index" if by_gap else "matched tests" if by_matched else None
    # matched evidence is found in-sample: it must also lower the held-out residual
    rss_drop = held_out_rss_drop(ev0, final, base.sigma) if by_matched and selected else None
    # a latency's second view, the gyroscope's timing, has its own held-out check
    gyro_drop = (gyro.get("held_out_drop") if by_matched and "latency" in selected and mt.gyro is not None
                 else None)
    v, basis = decide(detected_by, ev0.G, final.G if selected else ev0.G, thr0, selected, first,
                      matched=(ms.get("shrink", 0.0), ms.get("closed", False)) if by_matched else None,
                      rss_drop=rss_drop, gyro_drop=gyro_drop)
    s = basis.shrink
    # an explanation that leaves a dependence on a recorded aux signal is not complete (and a
    # partial one says which signal the rest follows)
    left = aux_left(eng, final, selected) if scope.accepted and v in ("explained", "partially_explained") else {}
    still = sorted((a for a, r in left.items() if r["fired"]), key=lambda a: -left[a]["t"])
    if still:
        log(f"  the residual still follows {', '.join(still)} given {' + '.join(selected)}")
        basis.notes.append(f"{v} -> partially_explained: the residual still follows {', '.join(still)}")
        v = "partially_explained"
    # a baseline that is not a calibration raises no gap: what it could still test is reported
    # beside the verdict
    on_testable = v
    if not scope.accepted:
        basis.notes.append(f"{v} on what could be tested -> baseline_rejected: {scope.reason}")
        v = "baseline_rejected"
    log(f"verdict {v}: {basis.rule}")
    lat = results.get("latency")
    if mt.gyro is not None and lat is not None and lat.magnitude is not None:
        lat.magnitude = {**lat.magnitude, "gyro_delay_ms": gyro["delay_ms"], "gyro_delay_se_ms": gyro["se_ms"]}
    ordered = sorted(results.values(), key=lambda r: (not r.testable, -(r.shrink if r.shrink is not None
                                                                          and np.isfinite(r.shrink) else -1e9)))
    fam = eng.gi.family_scores(ev0.z, ev0.weights) / eng.gi.norm
    info = {
        "samples": frame.n, "decimation": frame.decimation, "duration_s": frame.duration, "unit": frame.unit,
        "replicas": eng.R, "profile": profile, "seconds": time.perf_counter() - t_start,
        "baseline": {"hard_iron": base.fit.state.b.tolist(), "field": base.fit.state.F,
                     "noise": base.sigma[0], "noise_per_axis": base.sigma_axis.tolist(),
                     "burst_fraction": base.bursts["fraction"],
                     "inclination_deg": inclination_deg(base.fit.state.dip0) if frame.acc_unit is not None else None,
                     "inclination_convention": INCLINATION_CONVENTION if frame.acc_unit is not None else None,
                     "field_gravity_angle_deg": float(np.degrees(base.fit.state.dip0))
                     if frame.acc_unit is not None else None,
                     "calibration": {"accepted": scope.accepted, "reason": scope.reason or None,
                                     "rejection": None if scope.rejection is None else scope.rejection.to_json(),
                                     "quality": scope.quality}},
        "scope": scope.to_json(eng.gi.off, on_testable),
        "family_gaps": {n: g for n, g in zip(eng.gi.names, fam)},
        "detected_by": ("gap index" if by_gap else "matched tests" if by_matched else None),
        "matched_tests": {"level": mt.level, "fired": fired, "tests": mt.summary(),
                          **({k: ms[k] for k in ("shrink", "closed") if k in ms} if ms else {})},
        "aux_left": {"checked": bool(left), "tests": left, "still_followed": still},
        "gyro_timing": gyro,
        "aux_used": list(frame.aux), "aux_ignored": frame.aux_notes, "bad_rows": frame.bad_rows,
    }
    dropped = [{"name": n, "reason": "left out of the library (exclude)"} for n in sorted(exclude)]
    dropped += [{"name": n, "reason": f"left out with {', '.join(xs)}, which its form holds as a special case"}
                for n, xs in with_it.items()]
    dropped += [{"name": r.name, "reason": r.reason} for r in ordered if not r.testable]
    return Diagnosis(verdict=v, gap_before=ev0.G, gap_after=final.G if selected else ev0.G,
                     threshold=thr0, shrink=s, where=_where(eng, ev0),
                     effects=ordered, ambiguous_with=ambiguous, selected=selected, excluded=sorted(exclude),
                     info=info, basis=basis, dropped=dropped, attitude=att_diag, engine=eng,
                     evaluations={"baseline": ev0, "final": final})
