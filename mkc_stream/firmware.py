"""ctypes wrapper of the C99 reference port (firmware_ref/), and the Python-vs-C cross-check.

    from mkc_stream.firmware import CMagCalibrator, CStreamingMKC
    cal = CMagCalibrator(window=256, estep_every=32, precision="double")   # or "float"
    cal.update(raw)                      # raw (T, 3), as MagCalibrator.update
    cal.accepted.hard_iron, cal.status_reason()

The shared objects firmware_ref/build/libmkc_{double,float}.so are built on demand with `make` (a C
compiler and make are needed; FirmwareUnavailable says why when they are not). The objects here
mirror StreamingMKC and MagCalibrator closely enough for tests and tools; they are not a second
production API.

Cross-checking: `python_checkpoints` runs MagCalibrator and records its state after every E-step
checkpoint; `c_checkpoints` does the same with the C port; `compare_checkpoints` reports the largest
relative difference per quantity (see TOLERANCES for what "equal" means per precision).
"""
from __future__ import annotations

import ctypes as C
import os
import pathlib
import shutil
import subprocess
import threading
from dataclasses import dataclass

import numpy as np

FIRMWARE_DIR = pathlib.Path(__file__).resolve().parents[1] / "firmware_ref"
BUILD_DIR = FIRMWARE_DIR / "build"
PRECISIONS = ("double", "float")

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

QUALITY_KEYS = ("residual_rms", "residual_rms_all", "norm_spread", "norm_spread_inliers", "coverage",
                "outlier_fraction", "condition")

# field ids of mkc_get / mkc_set (include/mkc.h)
(F_THETA, F_SIGMA, F_D, F_A, F_HES, F_C, F_COND, F_LAST_F, F_CNT, F_NORMAL_A, F_NORMAL_B, F_RAW, F_C0S0, F_X, F_Y,
 F_L, F_DEQ, F_XS, F_TPREV, F_SLOT_AGE, F_SLOT_CELL, F_CELL_COUNT, F_MAG_FLAGS) = range(23)
REASON_NONE, REASON_INITIAL, REASON_PENDING, REASON_WINDOW, REASON_COVERAGE_WAIT, REASON_NOT_FINITE, \
    REASON_INDEFINITE, REASON_EMPTY, REASON_SINGULAR, REASON_REJECTED = range(10)
FAIL_COVERAGE, FAIL_CONDITION, FAIL_OUTLIERS, FAIL_RESIDUAL, FAIL_FIELD_RANGE, FAIL_FIELD_NONPOSITIVE = \
    1, 2, 4, 8, 16, 32
FAIL_DISAGREEMENT = 64
NOT_CALIBRATED = 7


class FirmwareUnavailable(RuntimeError):
    """The C port cannot be built or loaded here (no compiler, no make, no source tree)."""


# ----------------------------------------------------------------------------------------------
# building and loading
# ----------------------------------------------------------------------------------------------

def toolchain_problem() -> str | None:
    """None when the C port can be built here, else the reason it cannot."""
    if not (FIRMWARE_DIR / "Makefile").is_file():
        return f"the C sources are not here ({FIRMWARE_DIR} has no Makefile; an installed package has no firmware_ref/)"
    if shutil.which("make") is None:
        return "no `make` on PATH"
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        return f"no C compiler: `{cc}` is not on PATH (set CC)"
    return None


_build_lock = threading.Lock()


def build(*targets: str) -> None:
    """Run `make -C firmware_ref TARGETS` (default: all). Raises FirmwareUnavailable on failure."""
    why = toolchain_problem()
    if why:
        raise FirmwareUnavailable(why)
    with _build_lock:
        proc = subprocess.run(["make", "-C", str(FIRMWARE_DIR), *targets], capture_output=True, text=True)
    if proc.returncode != 0:
        raise FirmwareUnavailable(f"make -C firmware_ref {' '.join(targets)} failed:\n{proc.stdout[-3000:]}"
                                  f"{proc.stderr[-3000:]}")


def binary_path(name: str) -> pathlib.Path:
    return BUILD_DIR / name


def replay_path(precision: str = "double", sanitize: bool = False) -> pathlib.Path:
    name = "mkc_replay" if precision == "double" else "mkc_replay_float"
    return BUILD_DIR / ("asan" if sanitize else "") / name


class _MagReason(C.Structure):
    _fields_ = [("code", C.c_int32), ("fails", C.c_uint32), ("v", C.c_double * 6)]


class _Lib:
    """A loaded libmkc_*.so with its prototypes and the ctypes mirrors of the public structs."""

    def __init__(self, precision: str, path: pathlib.Path | None = None):
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}")
        path = path or BUILD_DIR / f"libmkc_{precision}.so"
        self.path = path
        self.dll = dll = C.CDLL(str(path))
        dll.mkc_build_info.argtypes = [C.POINTER(C.c_long), C.c_int]
        info = (C.c_long * 9)()
        dll.mkc_build_info(info, 9)
        self.N, self.M, self.W, self.K, rb, ab, eb, self.sizeof_stream, self.sizeof_mag = list(info)
        self.precision = precision
        self.real = C.c_double if rb == 8 else C.c_float
        self.ereal = C.c_double if eb == 8 else C.c_float
        self.dtype = np.float64 if rb == 8 else np.float32
        self.real_bytes, self.acc_bytes, self.ereal_bytes = rb, ab, eb
        real = self.real

        class Config(C.Structure):
            _fields_ = [("n", C.c_int), ("m", C.c_int), ("window", C.c_int), ("estep_every", C.c_int),
                        ("fp_rounds", C.c_int), ("estep_max_iter", C.c_int), ("refactor_every", C.c_int),
                        ("min_samples", C.c_int)] + [(k, C.c_double) for k in (
                            "sigma_lo", "sigma_hi", "d_lo", "d_hi", "a_factor", "a", "estep_gtol", "fp_tol",
                            "sigma_start", "sigma_pull")]

        class Rules(C.Structure):
            _fields_ = [(k, real) for k in ("min_coverage", "max_condition", "max_outlier_fraction",
                                            "max_residual_rel", "field_lo_ut", "field_hi_ut",
                                            "max_disagreement_rel")]

        class MagConfig(C.Structure):
            _fields_ = [("stream", Config), ("policy", C.c_int), ("unit_ut", C.c_int), ("init_samples", C.c_int),
                        ("rules", Rules)]

        class Calibration(C.Structure):
            _fields_ = [("hard_iron", real * 3), ("soft_iron", real * 9), ("field", real), ("sigma", real),
                        ("d", real), ("quality", real * 7), ("valid", C.c_int32), ("accepted", C.c_int32),
                        ("reason", _MagReason), ("samples_seen", C.c_int64), ("esteps", C.c_int64)]

        class Event(C.Structure):
            _fields_ = [("samples_seen", C.c_int64), ("esteps", C.c_int64), ("accepted", C.c_int32),
                        ("has_calibration", C.c_int32), ("reason", _MagReason), ("hard_iron", real * 3),
                        ("field", real), ("coverage", real), ("outlier_fraction", real)]

        self.Config, self.Rules, self.MagConfig, self.Calibration, self.Event = Config, Rules, MagConfig, Calibration, Event
        vp, rp = C.c_void_p, C.POINTER(real)
        i8p = C.POINTER(C.c_int8)
        self.Listener = C.CFUNCTYPE(None, C.c_void_p, C.c_void_p)
        protos = {
            "mkc_config_default": (None, [C.POINTER(Config), C.c_int, C.c_int]),
            "mkc_stream_init": (C.c_int, [vp, C.POINTER(Config), rp, rp, rp]),
            "mkc_stream_learn_one": (C.c_int, [vp, rp, rp, C.c_int]),
            "mkc_stream_learn_many": (C.c_int, [vp, rp, rp, C.c_long, i8p]),
            "mkc_mag_config_default": (None, [C.POINTER(MagConfig)]),
            "mkc_mag_init": (C.c_int, [vp, C.POINTER(MagConfig)]),
            "mkc_mag_set_listener": (None, [vp, self.Listener, vp]),
            "mkc_mag_push": (C.c_int, [vp, real, real, real]),
            "mkc_mag_push_many": (C.c_int, [vp, rp, C.c_long, i8p]),
            "mkc_mag_apply": (C.c_int, [vp, rp, rp]),
            "mkc_mag_status_reason": (None, [vp, C.POINTER(_MagReason)]),
            "mkc_mag_counts": (None, [vp, C.POINTER(C.c_int64), C.POINTER(C.c_int64)]),
            "mkc_get": (C.c_int, [vp, C.c_int, C.c_int, C.POINTER(C.c_double), C.c_int]),
            "mkc_set": (C.c_int, [vp, C.c_int, C.c_int, C.POINTER(C.c_double), C.c_int]),
            "mkc_mag_get_calibration": (C.POINTER(Calibration), [vp, C.c_int]),
            "mkc_mag_get_event": (C.POINTER(Event), [vp]),
            "mkc_mag_get_info": (C.c_int, [vp, C.POINTER(C.c_int64), C.c_int]),
        }
        for name, (res, args) in protos.items():
            fn = getattr(dll, name)
            fn.restype = res
            fn.argtypes = args

    def ptr(self, a: np.ndarray):
        return a.ctypes.data_as(C.POINTER(self.real))


_libs: dict[str, _Lib] = {}


def load(precision: str = "double", rebuild: bool = True) -> _Lib:
    """The loaded library of one precision; runs `make` first (cheap when up to date).

    precision "bench": the double build with the firmware capacities of mkc_config.h (n = 9, m = 1,
    W = 256), for timing beside Numba (tools/bench_firmware.py)."""
    if precision in _libs:
        return _libs[precision]
    if precision == "bench":
        build("build/libmkc_bench.so")
        _libs[precision] = _Lib("double", BUILD_DIR / "libmkc_bench.so")
        return _libs[precision]
    if rebuild:
        build(f"build/libmkc_{precision}.so")
    elif not (BUILD_DIR / f"libmkc_{precision}.so").is_file():
        raise FirmwareUnavailable(f"{BUILD_DIR}/libmkc_{precision}.so is not built (make -C firmware_ref)")
    _libs[precision] = _Lib(precision)
    return _libs[precision]


def _aligned_state(nbytes: int):
    buf = np.zeros(nbytes + 64, dtype=np.uint8)
    off = (-buf.ctypes.data) % 64
    return buf, buf.ctypes.data + off


# ----------------------------------------------------------------------------------------------
# StreamingMKC-like
# ----------------------------------------------------------------------------------------------

def _fill_config(lib, cfg, n, m, window, estep_every, config: dict):
    lib.dll.mkc_config_default(C.byref(cfg), n, m)
    cfg.window, cfg.estep_every = window, estep_every
    for k, v in config.items():
        if not hasattr(cfg, k) or k in ("n", "m"):
            raise TypeError(f"unknown stream setting {k!r}")
        setattr(cfg, k, v)


class CStreamingMKC:
    """The C port's generic stream, as StreamingMKC(n, m, window, estep_every, sigma, d, theta0, **config)."""

    def __init__(self, n, m=1, window=256, estep_every=32, sigma=None, d=None, theta0=None, precision="double",
                 **config):
        self.lib = lib = load(precision)
        if sigma is not None and "sigma_start" not in config:
            config["sigma_start"] = float(np.max(sigma))
        self.n, self.m, self.window = n, m, window
        self._cfg = lib.Config()
        _fill_config(lib, self._cfg, n, m, window, estep_every, config)
        self._sigma0 = None if sigma is None else np.ascontiguousarray(np.broadcast_to(sigma, (m,)), lib.dtype)
        self._d0 = None if d is None else np.ascontiguousarray(np.broadcast_to(d, (m,)), lib.dtype)
        self._theta0 = None if theta0 is None else np.ascontiguousarray(theta0, lib.dtype)
        self.reset()

    def reset(self):
        lib = self.lib
        self._buf, self._addr = _aligned_state(lib.sizeof_stream)
        args = [None if a is None else lib.ptr(a) for a in (self._sigma0, self._d0, self._theta0)]
        st = lib.dll.mkc_stream_init(self._addr, C.byref(self._cfg), *args)
        if st != 0:
            raise ValueError(f"mkc_stream_init: bad configuration (status {st})")
        return self

    def learn_one(self, x, y, slot=-1) -> int:
        x = np.ascontiguousarray(x, self.lib.dtype).reshape(self.m * self.n)
        y = np.ascontiguousarray(y, self.lib.dtype).reshape(self.m)
        return self.lib.dll.mkc_stream_learn_one(self._addr, self.lib.ptr(x), self.lib.ptr(y), slot)

    def learn_many(self, X, Y) -> np.ndarray:
        X = np.ascontiguousarray(X, self.lib.dtype).reshape(-1, self.m, self.n)
        Y = np.ascontiguousarray(Y, self.lib.dtype).reshape(-1, self.m)
        status = np.empty(X.shape[0], dtype=np.int8)
        self.lib.dll.mkc_stream_learn_many(self._addr, self.lib.ptr(X), self.lib.ptr(Y), X.shape[0],
                                           status.ctypes.data_as(C.POINTER(C.c_int8)))
        return status

    def get(self, which: int) -> np.ndarray:
        return _get(self.lib, self._addr, 0, which)

    @property
    def theta(self):
        return self.get(F_THETA)

    @property
    def cnt(self):
        return self.get(F_CNT).astype(np.int64)


def _get(lib, addr, kind, which):
    n = lib.dll.mkc_get(addr, kind, which, None, 0)
    if n < 0:
        raise ValueError(f"mkc_get: no field {which}")
    out = np.zeros(max(n, 1))
    lib.dll.mkc_get(addr, kind, which, out.ctypes.data_as(C.POINTER(C.c_double)), n)
    return out[:n]


# ----------------------------------------------------------------------------------------------
# MagCalibrator-like
# ----------------------------------------------------------------------------------------------

def _pct0(x):
    return f"{x:.0%}"


def reason_text(code: int, fails: int, v, rules=None) -> str:
    """MagCalibrator's reason strings (calib/streaming.py, calib/acceptance.py) from a C reason code."""
    from .calib import acceptance as A
    from .calib.streaming import MagCalibrator

    rules = rules or A.AcceptanceRules()
    if code == REASON_NONE:
        return ""
    if code == REASON_INITIAL:
        return "warming up: not enough samples yet"
    if code == REASON_PENDING:
        return f"warming up: {int(v[0])}/{int(v[1])} samples"
    if code == REASON_WINDOW:
        return f"warming up: {int(v[0])}/{int(v[1])} samples in the window"
    if code == REASON_COVERAGE_WAIT:
        return (f"waiting for orientation coverage ({v[0]:.0%} of the sphere around a sphere fit "
                f"< {MagCalibrator.MIN_SPHERE_COVERAGE:.0%}): rotate the sensor through all axes")
    if code == REASON_NOT_FINITE:
        return "trial is not an ellipsoid: ellipsoid parameters are not finite"
    if code == REASON_INDEFINITE:
        return ("trial is not an ellipsoid: the fitted quadric is not an ellipsoid: A is indefinite or singular "
                f"(eigenvalues {[float(x) for x in v[:3]]}); the data do not cover enough orientations, "
                "or the disturbances dominate")
    if code == REASON_EMPTY:
        return f"trial is not an ellipsoid: the fitted quadric is an empty or imaginary ellipsoid (1 + r0'A r0 = {v[0]:.3g})"
    if code == REASON_SINGULAR:
        return "trial is not an ellipsoid: Singular matrix"
    fails_txt = []
    cov, cond, out, rel, field = (float(x) for x in v[:5])
    if fails & FAIL_COVERAGE:
        fails_txt.append(A.coverage_failure(cov, rules))
    if fails & FAIL_CONDITION:
        fails_txt.append(A.condition_failure(cond, rules))
    if fails & FAIL_OUTLIERS:
        fails_txt.append(A.outlier_failure(out, rules))
    if fails & FAIL_RESIDUAL:
        fails_txt.append(A.residual_failure(rel, rules))
    if fails & FAIL_FIELD_RANGE:
        fails_txt.append(A.field_range_failure(field, rules))
    if fails & FAIL_FIELD_NONPOSITIVE:
        fails_txt.append(A.field_nonpositive_failure(field))
    if fails & FAIL_DISAGREEMENT:
        fails_txt.append(A.disagreement_failure(float(v[5]), rules))
    return "; ".join(fails_txt)


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


# The C port's calibration is the same record as the Python calibrator's (same fields, same apply).
# the C port's records are the reference's own types
from .calib.streaming import Calibration as CCalibration  # noqa: E402
from .calib.streaming import CheckpointEvent as CCheckpointEvent  # noqa: E402
from .units import is_microtesla  # noqa: E402


class CMagCalibrator:
    """The C port's MagCalibrator(window, estep_every, unit, policy, rules, init_samples, **stream_kw)."""

    def __init__(self, window=256, estep_every=32, unit="uT", policy="direction", rules=None, init_samples=None,
                 precision="double", keep_history=True, on_checkpoint=None, **stream_kw):
        from .calib.acceptance import AcceptanceRules

        self.lib = lib = load(precision)
        self.precision = precision
        self.unit, self.policy, self.keep_history = unit, policy, keep_history
        self.rules = rules or AcceptanceRules()
        self._cfg = lib.MagConfig()
        lib.dll.mkc_mag_config_default(C.byref(self._cfg))
        _fill_config(lib, self._cfg.stream, 9, 1, window, estep_every, stream_kw)
        self._cfg.policy = {"fifo": 0, "direction": 1}[policy]
        self._cfg.unit_ut = int(is_microtesla(unit))
        self._cfg.init_samples = int(init_samples or 0)
        r = self.rules
        for k, v in (("min_coverage", r.min_coverage), ("max_condition", r.max_condition),
                     ("max_outlier_fraction", r.max_outlier_fraction), ("max_residual_rel", r.max_residual_rel),
                     ("field_lo_ut", r.field_range_ut[0]), ("field_hi_ut", r.field_range_ut[1]),
                     ("max_disagreement_rel", r.max_disagreement_rel)):
            setattr(self._cfg.rules, k, v)
        self.on_checkpoint = on_checkpoint
        self._listener = lib.Listener(self._on_checkpoint)
        self.reset()

    def reset(self):
        lib = self.lib
        self._buf, self._addr = _aligned_state(lib.sizeof_mag)
        st = lib.dll.mkc_mag_init(self._addr, C.byref(self._cfg))
        if st != 0:
            raise ValueError(f"mkc_mag_init: bad configuration (status {st})")
        lib.dll.mkc_mag_set_listener(self._addr, self._listener, None)
        self.history = []
        self._events = []
        return self

    def _on_checkpoint(self, user, cal):
        ev = self.lib.dll.mkc_mag_get_event(self._addr).contents
        reason = reason_text(ev.reason.code, ev.reason.fails, list(ev.reason.v), self.rules)
        if ev.has_calibration:
            e = CCheckpointEvent(int(ev.samples_seen), int(ev.esteps), bool(ev.accepted), reason,
                                 np.array(ev.hard_iron[:], float), float(ev.field), float(ev.coverage),
                                 float(ev.outlier_fraction))
        else:
            e = CCheckpointEvent(int(ev.samples_seen), int(ev.esteps), False, reason)
        self._events.append(e)
        if self.keep_history:
            self.history.append(e)
        if self.on_checkpoint is not None:
            self.on_checkpoint(self)

    def update(self, mags) -> list:
        mags = np.ascontiguousarray(np.atleast_2d(np.asarray(mags, dtype=np.float64)))
        if mags.ndim != 2 or mags.shape[1] != 3:
            raise ValueError(f"magnetometer samples must have shape (T, 3); got {mags.shape}")
        with np.errstate(over="ignore"):          # float build: huge values become inf, rejected in C
            m = np.ascontiguousarray(mags, self.lib.dtype)
        self._events = []
        self.lib.dll.mkc_mag_push_many(self._addr, self.lib.ptr(m), m.shape[0], None)
        return self._events

    # -- inspection ---------------------------------------------------------------------------
    def get(self, which: int) -> np.ndarray:
        return _get(self.lib, self._addr, 1, which)

    def _calibration(self, accepted: bool):
        p = self.lib.dll.mkc_mag_get_calibration(self._addr, int(accepted))
        if not p:
            return None
        c = p.contents
        reason = reason_text(c.reason.code, c.reason.fails, list(c.reason.v), self.rules)
        return CCalibration(np.array(c.hard_iron[:], float), np.array(c.soft_iron[:], float).reshape(3, 3),
                            float(c.field), float(c.sigma), float(c.d),
                            {k: float(v) for k, v in zip(QUALITY_KEYS, c.quality)}, bool(c.accepted), reason,
                            int(c.samples_seen), int(c.esteps))

    @property
    def trial(self):
        return self._calibration(False)

    @property
    def accepted(self):
        return self._calibration(True)

    def info(self) -> dict:
        out = (C.c_int64 * 10)()
        self.lib.dll.mkc_mag_get_info(self._addr, out, 10)
        keys = ("first_accepted_at", "checkpoints", "provisional", "failed", "pending", "init_samples", "policy",
                "unit_ut", "misfit", "has_confirmed")
        return dict(zip(keys, (int(v) for v in out)))

    @property
    def first_accepted_at(self):
        v = self.info()["first_accepted_at"]
        return None if v < 0 else v

    @property
    def theta(self):
        return self.get(F_THETA)

    @property
    def cnt(self):
        return self.get(F_CNT).astype(np.int64)

    def status_reason(self) -> str:
        r = _MagReason()
        self.lib.dll.mkc_mag_status_reason(self._addr, C.byref(r))
        return reason_text(r.code, r.fails, list(r.v), self.rules) or "accepted"

    def counts(self) -> dict:
        s, b = C.c_int64(), C.c_int64()
        self.lib.dll.mkc_mag_counts(self._addr, C.byref(s), C.byref(b))
        return {"samples": int(s.value), "bad_frames": int(b.value), "drops": 0, "gaps": 0}

    def weights(self):
        raw = self.get(F_RAW).reshape(-1, 3)
        return raw, self.get(F_C) * self.get(F_D)[0] ** 2

    def apply(self, raw):
        acc = self.accepted
        if acc is None:
            from .calib.streaming import NotCalibratedError

            raise NotCalibratedError(f"no calibration accepted yet ({self.status_reason()})")
        return acc.apply(raw)

    def state_is_finite(self) -> bool:
        """No NaN/inf in any float field of the state that the estimate depends on."""
        fields = (F_THETA, F_SIGMA, F_D, F_A, F_HES, F_C, F_NORMAL_A, F_NORMAL_B, F_RAW, F_C0S0, F_X)
        return all(np.isfinite(self.get(f)).all() for f in fields)


# ----------------------------------------------------------------------------------------------
# the feedback path
# ----------------------------------------------------------------------------------------------
#
# The sphere fit and the eigen-decompositions whose results flow back into MagCalibrator's state
# are bit-reproducible in the reference itself (mkc_stream/calib/portable.py, the C port's
# algorithms operation for operation), because the stream is sensitive to their last bits
# (firmware_ref/README.md, "Why portable feedback"). Nothing needs swapping any more.

class portable_feedback:
    """Kept for scripts written against the first port: a no-op context manager now."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


# ----------------------------------------------------------------------------------------------
# cross-checking: the state at every checkpoint, Python and C
# ----------------------------------------------------------------------------------------------

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
    from .calib.streaming import MagCalibrator
    from .kernels import window as K

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
        cal.update(mags[s:s + step])
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
    cal.update(mags)
    return recs, cal


def reference_state(cal) -> dict:
    """Everything MagCalibrator's next checkpoint depends on, as float64/int64 arrays (the window's
    count samples only). With `next_index` = samples consumed (seen + rejected; valid once the first
    normalisation's pending samples are in and when no sample was rejected during it)."""
    from .kernels import window as K

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
        cal.update(mags[t])
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
    from .kernels import window as K
    from .stream import StreamingMKC

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


# ----------------------------------------------------------------------------------------------
# golden-vector inputs: stored as data, one file per vector (tools/gen_golden.py writes them once)
# ----------------------------------------------------------------------------------------------

REPO_ROOT = FIRMWARE_DIR.parent
GOLDEN_DIR = REPO_ROOT / "tests" / "data" / "golden"

#: the arrays a vector's input consists of, by kind; each is stored as little-endian float64
INPUT_KEYS = {"mag": ("input_mags", "input_t"), "linear": ("input_X", "input_Y")}


def input_sha256(arrays) -> str:
    """SHA-256 of the input arrays' little-endian float64 bytes, in order (the stored checksum)."""
    import hashlib

    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def stored_input(meta: dict) -> dict:
    """A golden vector's input as stored in its file, checked against the index's checksum.

    The input is never regenerated at test time: a synthetic stream rebuilt through BLAS differs in
    its last bits from one CPU to another, and the vectors' checkpoints would no longer apply.
    Magnetometer vectors give {"mags" (T, 3), "t" (T,), "unit"}; linear ones {"X" (T, m, n), "Y" (T, m)}.
    """
    with np.load(GOLDEN_DIR / meta["input_file"]) as z:
        arrays = [z[k] for k in INPUT_KEYS[meta["kind"]]]
    digest = input_sha256(arrays)
    if digest != meta["input_sha256"]:
        raise ValueError(f"golden vector {meta['name']}: stored input fails its checksum "
                         f"({digest[:16]} != {meta['input_sha256'][:16]}); regenerate: python tools/gen_golden.py")
    arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in arrays]
    if meta["kind"] == "mag":
        return {"mags": arrays[0], "t": arrays[1], "unit": meta["unit"]}
    return {"X": arrays[0], "Y": arrays[1]}
