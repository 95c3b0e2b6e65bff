"""The Python-vs-C cross-check: the state at every checkpoint, Python and C, and how far apart they are.

`python_checkpoints` runs MagCalibrator and records its state after every E-step checkpoint;
`c_checkpoints` does the same with the C port; `compare_checkpoints` reports the largest relative
difference per quantity (see TOLERANCES for what "equal" means per precision). `segment_comparison`
restarts the C port from the reference's state (teacher forcing); `stream_records_python` /
`stream_records_c` do the same for the generic StreamingMKC.
"""
from __future__ import annotations

import ctypes as C
from dataclasses import dataclass

import numpy as np

from .bindings import (F_A, F_C, F_C0S0, F_CELL_COUNT, F_CNT, F_COND, F_D, F_DEQ, F_HES, F_L, F_LAST_F,
                       F_MAG_FLAGS, F_NORMAL_A, F_NORMAL_B, F_RAW, F_SIGMA, F_SLOT_AGE, F_SLOT_CELL, F_THETA,
                       F_TPREV, F_XS, QUALITY_KEYS, CMagCalibrator, CStreamingMKC)

#: Relative tolerances of the cross-check, per precision and quantity: max |c - py| / max |py| over
#: the quantity's entries at each checkpoint. The double build mirrors the Python kernels operation by
#: operation (the kernels are bitwise equal); what remains is LAPACK/BLAS (eigh, solve, lstsq, matmul)
#: versus the port's Jacobi / elimination / normal equations at ~1e-15, amplified by the estimate's
#: sensitivity. The condition number is an eigenvalue ratio, computed to ~cond * eps by either method.
#: The float build rounds every stored value to 24 bits: 1e-4 on theta and the calibration.
TOLERANCES = {
    "double": {"theta": 1e-9, "sigma": 1e-9, "d": 1e-9, "a": 1e-9, "c0s0": 1e-9, "hard_iron": 1e-9,
               "soft_iron": 1e-9, "field": 1e-9, "quality": 1e-9, "condition": 1e-6},
    "float": {"theta": 1e-4, "sigma": 1e-3, "d": 1e-3, "a": 1e-3, "c0s0": 1e-4, "hard_iron": 1e-4,
              "soft_iron": 1e-4, "field": 1e-4, "quality": 1e-2, "condition": 1e-2},
}

#: quantities whose tolerance is part of the acceptance criteria (theta and the calibration)
CORE_QUANTITIES = ("theta", "hard_iron", "soft_iron", "field")


def _record(seen, esteps, status, theta, sigma, d, a, c0, s0, event_accepted, reason, trial):
    rec = {"samples_seen": int(seen), "esteps": int(esteps), "status": int(status),
           "theta": np.array(theta, float), "sigma": float(sigma), "d": float(d), "a": float(a),
           "c0s0": np.array([*c0, s0], float), "accepted": bool(event_accepted), "reason": reason,
           "has_trial": trial is not None}
    if trial is not None:
        rec.update({"hard_iron": np.array(trial.hard_iron, float), "soft_iron": np.array(trial.soft_iron, float),
                    "field": float(trial.field),
                    "quality": np.array([trial.quality[k] for k in QUALITY_KEYS[:-1]], float),
                    "condition": float(trial.quality["condition"])})
    return rec


def python_checkpoints(mags, window=256, estep_every=32, unit="uT", chunk=None, portable=True, capture_state=False,
                       **kw):
    """Run MagCalibrator over mags; the state after every checkpoint (list of dicts) and the calibrator.

    chunk: feed in chunks of this many samples (None: one update() call), as `calibrate --stream` does.
    portable: ignored (the reference's feedback path is bit-reproducible itself; calib/portable.py).
    capture_state: each record also holds "state", the whole calibrator state (reference_state), from
    which c_segment restarts the C port.
    """
    from ..calib.streaming import MagCalibrator
    from ..kernels import window as K

    recs = []

    def checkpoint(cal):
        ev = cal.last_event
        st = cal.stream.views()
        trial = cal.trial if (ev.hard_iron is not None) else None
        recs.append(_record(st["cnt"][K.C_SEEN], st["cnt"][K.C_ESTEPS], st["cnt"][K.C_STATUS], st["theta"],
                            st["sigma"][0], st["d"][0], st["a"][0], cal.c0, cal.s0, ev.accepted, ev.reason, trial))
        if capture_state:
            recs[-1]["state"] = reference_state(cal)

    cal = MagCalibrator(window=window, estep_every=estep_every, unit=unit, on_checkpoint=checkpoint, **kw)
    mags = np.asarray(mags, dtype=np.float64)
    step = len(mags) if not chunk else chunk
    for s in range(0, max(len(mags), 1), max(step, 1)):
        cal.learn_many(mags[s:s + step])
    return recs, cal


def _c_record(c) -> dict:
    """The record of the C calibrator's checkpoint that just happened (python_checkpoints' format)."""
    ev = c._events[-1]
    cnt = c.cnt
    trial = c.trial if ev.hard_iron is not None else None
    c0s0 = c.get(F_C0S0)
    return _record(cnt[2], cnt[4], cnt[6], c.theta, c.get(F_SIGMA)[0], c.get(F_D)[0], c.get(F_A)[0],
                   c0s0[:3], c0s0[3], ev.accepted, ev.reason, trial)


def c_checkpoints(mags, window=256, estep_every=32, unit="uT", precision="double", **kw):
    """The same records from the C port."""
    recs = []

    def on_checkpoint(c):
        recs.append(_c_record(c))

    cal = CMagCalibrator(window=window, estep_every=estep_every, unit=unit, precision=precision,
                         on_checkpoint=on_checkpoint, **kw)
    cal.learn_many(mags)
    return recs, cal


def reference_state(cal) -> dict:
    """Everything MagCalibrator's next checkpoint depends on, as float64/int64 arrays (the window's
    count samples only). With `next_index` = samples consumed (seen + rejected; valid once the first
    normalisation's pending samples are in and when no sample was rejected during it)."""
    from ..kernels import window as K

    st = cal.stream.views()
    count = int(st["cnt"][K.C_COUNT])
    conf = cal._confirmed
    flags = [float(cal.provisional), float(cal._failed), float(getattr(cal, "_misfit", 0)),
             float(conf is not None), *(list(map(float, conf[0])) if conf is not None else [0.0] * 3),
             float(conf[1]) if conf is not None else 0.0,
             float(-1 if cal.first_accepted_at is None else cal.first_accepted_at)]
    return {"cnt": st["cnt"].copy(), "theta": st["theta"].copy(), "sigma": st["sigma"].copy(),
            "d": st["d"].copy(), "a": st["a"].copy(), "Hes": st["Hes"].ravel().copy(),
            "C": st["C"][:count, 0].copy(), "A": st["A"].ravel().copy(), "b": st["b"].copy(),
            "L": st["L"].ravel().copy(), "D": st["D"].copy(), "xs": st["xs"].copy(), "tprev": st["tprev"].copy(),
            "fst": st["fst"].copy(), "raw": cal.raw[:count].ravel().copy(),
            "slot_age": cal.slot_age[:count].copy(), "slot_cell": cal.slot_cell[:count].copy(),
            "cell_count": cal.cell_count.copy(), "c0s0": np.array([*cal.c0, cal.s0]),
            "flags": np.array(flags), "next_index": int(st["cnt"][K.C_SEEN] + st["cnt"][K.C_REJECTED])}


_STATE_FIELDS = (("cnt", F_CNT), ("c0s0", F_C0S0), ("theta", F_THETA), ("sigma", F_SIGMA), ("d", F_D), ("a", F_A),
                 ("Hes", F_HES), ("C", F_C), ("A", F_NORMAL_A), ("b", F_NORMAL_B), ("L", F_L), ("D", F_DEQ),
                 ("xs", F_XS), ("tprev", F_TPREV), ("raw", F_RAW), ("slot_age", F_SLOT_AGE),
                 ("slot_cell", F_SLOT_CELL), ("cell_count", F_CELL_COUNT), ("flags", F_MAG_FLAGS))


def load_reference_state(cal: "CMagCalibrator", state: dict) -> None:
    """Put a reference_state() into a C calibrator (rounded to its precision): teacher forcing."""
    lib = cal.lib
    for key, which in _STATE_FIELDS:
        v = np.ascontiguousarray(state[key], dtype=np.float64)
        st = lib.dll.mkc_set(cal._addr, 1, which, v.ctypes.data_as(C.POINTER(C.c_double)), v.size)
        if st != 0:
            raise ValueError(f"mkc_set({key}) refused the state (status {st})")
    fst = np.asarray(state["fst"], dtype=np.float64)
    lib.dll.mkc_set(cal._addr, 1, F_COND, fst[:1].ctypes.data_as(C.POINTER(C.c_double)), 1)
    lib.dll.mkc_set(cal._addr, 1, F_LAST_F, fst[1:2].ctypes.data_as(C.POINTER(C.c_double)), 1)


def c_segment(mags, state: dict, window=256, estep_every=32, unit="uT", precision="float", **kw):
    """Start the C port from a reference state and feed mags from state["next_index"] until its next
    checkpoint; returns that checkpoint's record (None if the samples ran out)."""
    out = []

    def on_checkpoint(c):
        if not out:
            out.append(_c_record(c))

    cal = CMagCalibrator(window=window, estep_every=estep_every, unit=unit, precision=precision,
                         on_checkpoint=on_checkpoint, **kw)
    load_reference_state(cal, state)
    start = int(state["next_index"])
    for t in range(start, len(mags)):
        cal.learn_many(mags[t])
        if out:
            return out[0]
    return None


def well_posed(rec, min_coverage=0.5) -> bool:
    """A checkpoint whose trial is determined by its window: an ellipsoid, with the window's
    directions covering the acceptance predicate's minimum of the sphere. (On a window covering a
    third of the sphere the 9 parameters are ill-conditioned: float rounding moves them by ~1e-3.)"""
    return bool(rec["has_trial"]) and rec["quality"][QUALITY_KEYS.index("coverage")] >= min_coverage


def segment_comparison(mags, recs, window=256, estep_every=32, unit="uT", precision="float", anchors=None,
                       only_well_posed=True, **kw):
    """Teacher-forced comparison: for each reference checkpoint k with a captured state (anchors:
    the k to use; None: every k after the first normalisation, with a non-provisional state), start
    the C port from the state of checkpoint k and compare its next checkpoint with the reference's
    checkpoint k + 1 (only well-posed ones unless only_well_posed=False)."""
    pairs_py, pairs_c = [], []
    init = kw.get("init_samples") or min(window, 64)
    if anchors is None:
        anchors = [k for k in range(len(recs) - 1) if recs[k].get("state") is not None
                   and recs[k]["state"]["next_index"] >= init and recs[k]["state"]["flags"][0] == 0]
    for k in anchors:
        st = recs[k].get("state")
        if st is None or (only_well_posed and not well_posed(recs[k + 1])):
            continue
        rc = c_segment(mags, st, window, estep_every, unit, precision, **kw)
        if rc is None:
            continue
        pairs_py.append(recs[k + 1])
        pairs_c.append(rc)
    return compare_checkpoints(pairs_py, pairs_c)


def rel_diff(a, b) -> float:
    """max |a - b| / max |b| (0 when both are 0)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    diff = float(np.max(np.abs(a - b))) if b.size else 0.0
    if scale == 0.0:
        return diff
    return diff / scale


@dataclass
class Comparison:
    checkpoints_python: int
    checkpoints_c: int
    max_rel: dict            # quantity -> largest relative difference over all checkpoints
    where: dict              # quantity -> samples_seen of that largest difference
    mismatches: list         # structural differences (checkpoint index, accept decision, status, reason kind)

    def worst(self, quantities=None) -> float:
        keys = quantities or self.max_rel.keys()
        return max((self.max_rel[k] for k in keys if k in self.max_rel), default=0.0)

    def failures(self, precision="double", quantities=None) -> list:
        """Quantities beyond their tolerance, plus the structural mismatches."""
        tol = TOLERANCES[precision]
        keys = quantities or tol.keys()
        out = [f"{k}: max rel diff {self.max_rel[k]:.3g} > {tol[k]:.3g} (at sample {self.where[k]})"
               for k in keys if k in self.max_rel and not self.max_rel[k] <= tol[k]]
        return out + list(self.mismatches)


def compare_checkpoints(py: list, c: list, strict_structure=True) -> Comparison:
    """Per quantity, the largest relative difference over the checkpoints both runs share."""
    max_rel, where, mism = {}, {}, []
    if len(py) != len(c):
        mism.append(f"checkpoint count: python {len(py)}, C {len(c)}")
    for k, (p, q) in enumerate(zip(py, c)):
        if p["samples_seen"] != q["samples_seen"] or p["esteps"] != q["esteps"]:
            mism.append(f"checkpoint {k}: python at sample {p['samples_seen']} (E-step {p['esteps']}), "
                        f"C at {q['samples_seen']} ({q['esteps']})")
            break
        if strict_structure:
            if p["accepted"] != q["accepted"]:
                mism.append(f"checkpoint {k} (sample {p['samples_seen']}): accepted python {p['accepted']}, "
                            f"C {q['accepted']}")
            if p["has_trial"] != q["has_trial"]:
                mism.append(f"checkpoint {k} (sample {p['samples_seen']}): trial python {p['has_trial']}, "
                            f"C {q['has_trial']}")
            if reason_kind(p["reason"]) != reason_kind(q["reason"]):
                mism.append(f"checkpoint {k} (sample {p['samples_seen']}): reason python {p['reason']!r}, "
                            f"C {q['reason']!r}")
        keys = ["theta", "sigma", "d", "a", "c0s0"]
        if p["has_trial"] and q["has_trial"]:
            keys += ["hard_iron", "soft_iron", "field", "quality", "condition"]
        for key in keys:
            r = rel_diff(q[key], p[key])
            if not r <= max_rel.get(key, -1.0):
                max_rel[key] = r
                where[key] = p["samples_seen"]
    return Comparison(len(py), len(c), max_rel, where, mism)


def stream_records_python(X, Y, n, m, window, estep_every, **kw):
    """StreamingMKC over (X, Y): the state after every E-step checkpoint."""
    from ..kernels import window as K
    from ..stream import StreamingMKC

    est = StreamingMKC(n, m, window=window, estep_every=estep_every, **kw)
    recs = []
    st = est.views()          # read-only, and live: they follow the stream
    for k in range(X.shape[0]):
        e0 = int(st["cnt"][K.C_ESTEPS])
        status = est.learn_one(X[k], Y[k])
        if st["cnt"][K.C_ESTEPS] > e0:
            recs.append({"index": k, "status": int(status), "theta": st["theta"].copy(), "sigma": st["sigma"].copy(),
                         "d": st["d"].copy(), "a": st["a"].copy(), "cnt": st["cnt"].copy()})
    return recs, est


def stream_records_c(X, Y, n, m, window, estep_every, precision="double", **kw):
    est = CStreamingMKC(n, m, window=window, estep_every=estep_every, precision=precision, **kw)
    recs = []
    for k in range(X.shape[0]):
        e0 = est.cnt[4]
        status = est.learn_one(X[k], Y[k])
        cnt = est.cnt
        if cnt[4] > e0:
            recs.append({"index": k, "status": int(status), "theta": est.theta, "sigma": est.get(F_SIGMA),
                         "d": est.get(F_D), "a": est.get(F_A), "cnt": cnt})
    return recs, est


def reason_kind(text: str) -> str:
    """The part of a reason that does not depend on rounding (for comparing Python and C reasons)."""
    if not text:
        return "accepted"
    if text.startswith("trial is not an ellipsoid"):
        return "not an ellipsoid" + (": indefinite" if "indefinite" in text else
                                     ": empty" if "empty" in text else "")
    if text.startswith("waiting for orientation coverage"):
        return "waiting for coverage"
    if text.startswith("warming up"):
        return text
    parts = [p.split(" ")[0] + " " + p.split(" ")[1] for p in text.split("; ")]
    return "rejected: " + ", ".join(parts)
