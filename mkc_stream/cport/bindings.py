"""ctypes bindings of the C99 reference port: the loaded library, CStreamingMKC and CMagCalibrator.

    from mkc_stream.cport.bindings import CMagCalibrator, CStreamingMKC
    cal = CMagCalibrator(window=256, estep_every=32, precision="double")   # or "float"
    cal.learn_many(raw)                  # raw (T, 3), as MagCalibrator.learn_many
    cal.accepted.hard_iron, cal.status_reason()

The objects here mirror StreamingMKC and MagCalibrator closely enough for tests and tools; they are
not a second production API. The field ids (F_*) are those of mkc_get / mkc_set (include/mkc.h).
"""
from __future__ import annotations

import ctypes as C
import pathlib

import numpy as np

# the C port's calibration and checkpoint event are the reference's own types
from ..defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from ..calib.result import Calibration as CCalibration
from ..calib.streaming import CheckpointEvent as CCheckpointEvent
from ..units import is_microtesla
from .toolchain import BUILD_DIR, PRECISIONS, FirmwareUnavailable, build

QUALITY_KEYS = ("residual_rms", "residual_rms_all", "norm_spread", "norm_spread_inliers", "coverage",
                "outlier_fraction", "condition")

# field ids of mkc_get / mkc_set (include/mkc.h)
(F_THETA, F_SIGMA, F_D, F_A, F_HES, F_C, F_COND, F_LAST_F, F_CNT, F_NORMAL_A, F_NORMAL_B, F_RAW, F_C0S0, F_X, F_Y,
 F_L, F_DEQ, F_XS, F_TPREV, F_SLOT_AGE, F_SLOT_CELL, F_CELL_COUNT, F_MAG_FLAGS) = range(23)
REASON_NONE, REASON_INITIAL, REASON_PENDING, REASON_WINDOW, REASON_COVERAGE_WAIT, REASON_NOT_FINITE, \
    REASON_INDEFINITE, REASON_EMPTY, REASON_SINGULAR, REASON_REJECTED, REASON_MOTION_WAIT, REASON_DEGENERATE = range(12)
FAIL_COVERAGE, FAIL_CONDITION, FAIL_OUTLIERS, FAIL_RESIDUAL, FAIL_FIELD_RANGE, FAIL_FIELD_NONPOSITIVE = \
    1, 2, 4, 8, 16, 32
FAIL_DISAGREEMENT = 64
NOT_CALIBRATED = 7


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
        # mkc_api_real (mkc_config.h): the settings' and reason values' type, float only in the
        # all-float build (float storage, normal equations and E-step)
        self.api_real = api_real = C.c_float if (rb, ab, eb) == (4, 4, 4) else C.c_double
        self.dtype = np.float64 if rb == 8 else np.float32
        self.real_bytes, self.acc_bytes, self.ereal_bytes = rb, ab, eb
        real = self.real

        class Config(C.Structure):
            _fields_ = [("n", C.c_int), ("m", C.c_int), ("window", C.c_int), ("estep_every", C.c_int),
                        ("fp_rounds", C.c_int), ("estep_max_iter", C.c_int), ("refactor_every", C.c_int),
                        ("min_samples", C.c_int)] + [(k, api_real) for k in (
                            "sigma_lo", "sigma_hi", "d_lo", "d_hi", "a_factor", "a", "estep_gtol", "fp_tol",
                            "sigma_start", "sigma_pull")]

        class Rules(C.Structure):
            _fields_ = [(k, real) for k in ("min_coverage", "max_condition", "max_outlier_fraction",
                                            "max_residual_rel", "field_lo_ut", "field_hi_ut",
                                            "max_disagreement_rel")]

        class MagConfig(C.Structure):
            _fields_ = [("stream", Config), ("policy", C.c_int), ("unit_ut", C.c_int), ("init_samples", C.c_int),
                        ("rules", Rules), ("switching", C.c_int)]

        class MagReason(C.Structure):
            _fields_ = [("code", C.c_int32), ("fails", C.c_uint32), ("v", api_real * 6)]

        class Calibration(C.Structure):
            _fields_ = [("hard_iron", real * 3), ("soft_iron", real * 9), ("field", real), ("sigma", real),
                        ("d", real), ("quality", real * 7), ("valid", C.c_int32), ("accepted", C.c_int32),
                        ("reason", MagReason), ("samples_seen", C.c_int64), ("esteps", C.c_int64)]

        class Event(C.Structure):
            _fields_ = [("samples_seen", C.c_int64), ("esteps", C.c_int64), ("accepted", C.c_int32),
                        ("has_calibration", C.c_int32), ("reason", MagReason), ("hard_iron", real * 3),
                        ("field", real), ("coverage", real), ("outlier_fraction", real)]

        self.Config, self.Rules, self.MagConfig, self.Calibration, self.Event = Config, Rules, MagConfig, Calibration, Event
        self.MagReason = MagReason
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
            "mkc_mag_status_reason": (None, [vp, C.POINTER(MagReason)]),
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


class _CoreFields:
    """theta and the counters, read through the class's own get(): both C objects hold a core."""

    @property
    def theta(self):
        return self.get(F_THETA)

    @property
    def cnt(self):
        return self.get(F_CNT).astype(np.int64)


class CStreamingMKC(_CoreFields):
    """The C port's generic stream, as StreamingMKC(n, m, window, estep_every, sigma, d, theta0, **config)."""

    def __init__(self, n, m=1, window=DEFAULT_WINDOW, estep_every=DEFAULT_ESTEP_EVERY, sigma=None, d=None, theta0=None,
                 precision="double",
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

#: the C reason codes as Rejection codes (calib/result.py)
REJECTION_CODE = {REASON_INITIAL: "warming_up", REASON_PENDING: "warming_up", REASON_WINDOW: "warming_up",
                  REASON_COVERAGE_WAIT: "waiting_coverage", REASON_MOTION_WAIT: "waiting_motion",
                  REASON_NOT_FINITE: "not_ellipsoid", REASON_INDEFINITE: "not_ellipsoid", REASON_EMPTY: "not_ellipsoid",
                  REASON_SINGULAR: "not_ellipsoid", REASON_REJECTED: "rejected", REASON_DEGENERATE: "not_ellipsoid"}
#: the C predicate's fail bits as acceptance.CHECKS names, in the predicate's order
FAIL_NAMES = ((FAIL_COVERAGE, "coverage"), (FAIL_CONDITION, "condition"), (FAIL_OUTLIERS, "outliers"),
              (FAIL_RESIDUAL, "residual"), (FAIL_FIELD_RANGE, "field_range"),
              (FAIL_FIELD_NONPOSITIVE, "field_nonpositive"), (FAIL_DISAGREEMENT, "disagreement"))


def rejection_from_code(code: int, fails: int, v, rules=None):
    """The Rejection (calib/result.py) of a C reason: code, failed checks, values and the sentence
    MagCalibrator writes; None for MKC_REASON_NONE."""
    from ..calib.result import Rejection

    if code == REASON_NONE:
        return None
    text = reason_text(code, fails, v, rules)
    failed = tuple(name for bit, name in FAIL_NAMES if fails & bit) if code == REASON_REJECTED else ()
    if code == REASON_REJECTED:
        values = dict(zip(("coverage", "condition", "outlier_fraction", "residual_rel", "field"), map(float, v[:5])))
        if fails & FAIL_DISAGREEMENT:
            values["disagreement"] = float(v[5])
    elif code == REASON_COVERAGE_WAIT:
        values = {"coverage": float(v[0])}
    elif code == REASON_MOTION_WAIT:
        values = {"spread": float(v[0])}
    else:
        values = {}
    return Rejection(REJECTION_CODE.get(code, "rejected"), text, failed, values)


def reason_text(code: int, fails: int, v, rules=None) -> str:
    """MagCalibrator's reason strings (calib/streaming.py, calib/acceptance.py) from a C reason code."""
    from ..calib import acceptance as A
    from ..calib.streaming import MagCalibrator

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
        return A.coverage_wait_reason(v[0], MagCalibrator.MIN_SPHERE_COVERAGE)
    if code == REASON_MOTION_WAIT:
        return A.motion_wait_reason(v[0], MagCalibrator.MAX_SPHERE_SPREAD)
    if code == REASON_DEGENERATE:
        return A.degenerate_reason()
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
        below = bool(fails & FAIL_FIELD_RANGE) and field < rules.field_range_ut[0]
        fails_txt.append(A.residual_failure(rel, rules, below))
    if fails & FAIL_FIELD_RANGE:
        fails_txt.append(A.field_range_failure(field, rules))
    if fails & FAIL_FIELD_NONPOSITIVE:
        fails_txt.append(A.field_nonpositive_failure(field))
    if fails & FAIL_DISAGREEMENT:
        fails_txt.append(A.disagreement_failure(float(v[5]), rules))
    return "; ".join(fails_txt)


class CMagCalibrator(_CoreFields):
    """The C port's MagCalibrator(window, estep_every, unit, policy, rules, init_samples, switching, **stream_kw).

    switching: "pooled" or "paired" (the C port has no "latest"); None: the C library's default."""

    #: calib/streaming.py SWITCHING -> the C port's MKC_SWITCH_*
    SWITCHING = {"paired": 0, "pooled": 1}

    def __init__(self, window=DEFAULT_WINDOW, estep_every=DEFAULT_ESTEP_EVERY, unit="uT", policy="direction", rules=None,
                 init_samples=None, precision="double", keep_history=True, on_checkpoint=None, switching=None,
                 **stream_kw):
        from ..calib.acceptance import AcceptanceRules

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
        if switching is not None:
            if switching not in self.SWITCHING:
                raise ValueError(f"switching must be one of {sorted(self.SWITCHING)} in the C port; got {switching!r}")
            self._cfg.switching = self.SWITCHING[switching]
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

    def learn_one(self, mag) -> list:
        """Feed one raw sample (3,); the checkpoint events it produced (MagCalibrator.learn_one)."""
        return self.learn_many(np.reshape(np.asarray(mag, dtype=np.float64), (1, 3)))

    def learn_many(self, mags) -> list:
        """Feed raw samples (T, 3); the checkpoint events they produced (MagCalibrator.learn_many)."""
        mags = np.ascontiguousarray(np.atleast_2d(np.asarray(mags, dtype=np.float64)))
        if mags.ndim != 2 or mags.shape[1] != 3:
            raise ValueError(f"magnetometer samples must have shape (T, 3); got {mags.shape}")
        with np.errstate(over="ignore"):          # float build: huge values become inf, rejected in C
            m = np.ascontiguousarray(mags, self.lib.dtype)
        self._events = []
        self.lib.dll.mkc_mag_push_many(self._addr, self.lib.ptr(m), m.shape[0], None)
        return self._events

    #: the former name of learn_many, kept for one release
    update = learn_many

    # -- inspection ---------------------------------------------------------------------------
    def get(self, which: int) -> np.ndarray:
        return _get(self.lib, self._addr, 1, which)

    def _calibration(self, accepted: bool):
        p = self.lib.dll.mkc_mag_get_calibration(self._addr, int(accepted))
        if not p:
            return None
        c = p.contents
        return CCalibration(np.array(c.hard_iron[:], float), np.array(c.soft_iron[:], float).reshape(3, 3),
                            float(c.field), {k: float(v) for k, v in zip(QUALITY_KEYS, c.quality)}, bool(c.accepted),
                            rejection_from_code(c.reason.code, c.reason.fails, list(c.reason.v), self.rules),
                            channels=[{"sigma": float(c.sigma), "d": float(c.d)}],
                            samples_seen=int(c.samples_seen), esteps=int(c.esteps))

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


    def status(self):
        """None when accepted, else the Rejection (calib/result.py) of MagCalibrator.status()."""
        r = self.lib.MagReason()
        self.lib.dll.mkc_mag_status_reason(self._addr, C.byref(r))
        return rejection_from_code(r.code, r.fails, list(r.v), self.rules)

    def status_reason(self) -> str:
        r = self.status()
        return "accepted" if r is None else r.text

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
            from ..calib.streaming import NotCalibratedError

            raise NotCalibratedError(f"no calibration accepted yet ({self.status_reason()})")
        return acc.apply(raw)

    def state_is_finite(self) -> bool:
        """No NaN/inf in any float field of the state that the estimate depends on."""
        fields = (F_THETA, F_SIGMA, F_D, F_A, F_HES, F_C, F_NORMAL_A, F_NORMAL_B, F_RAW, F_C0S0, F_X)
        return all(np.isfinite(self.get(f)).all() for f in fields)
