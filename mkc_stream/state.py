"""The streaming estimator's fixed-size state: field for field the C struct of firmware_ref/.

Sizes depend only on the configuration (n parameters, m channels, window W), never on the number
of samples seen. `STATE_FIELDS` is the single source of truth for the layout: the C struct in
firmware_ref/include/mkc.h mirrors it (tests/test_firmware.py checks the field set) and its index
constants are generated from it by tools/gen_firmware_tables.py.
"""
from __future__ import annotations

import math
import operator
from dataclasses import asdict, dataclass, fields

import numpy as np

from ._validation import MKCInputError
from .defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from .kernels import STATUS_TEXT
from .kernels import window as K

STATE_VERSION = 2

#: Largest window a stream accepts: the state grows ~200 bytes per sample and channel-parameter
#: product (13 MB at 65536 for the ellipsoid), and a window beyond a minute of 1 kHz data only
#: slows the E-step (O(W) per checkpoint) without helping a calibration.
MAX_WINDOW = 65536
#: Largest state a configuration may ask for (n and m are otherwise unbounded): an absurd m or n
#: gets a clear error instead of a MemoryError or an allocation the machine cannot back.
MAX_STATE_BYTES = 1 << 30
#: The C port's configuration fields are C ints.
C_INT_MAX = 2**31 - 1


@dataclass(frozen=True)
class StreamConfig:
    n: int                        # parameters (9 for the ellipsoid)
    m: int = 1                    # residual channels
    window: int = DEFAULT_WINDOW  # W: samples kept
    estep_every: int = DEFAULT_ESTEP_EVERY   # K: E-step + rebuild every K samples
    # Fixed-point rounds per rebuild (stops early at fp_tol). One round per checkpoint: the
    # windows of consecutive checkpoints overlap by W - K samples, so the stream keeps iterating
    # Algorithm 1 across checkpoints; a second round costs as much as the E-step.
    fp_rounds: int = 1
    # BFGS iterations per channel per E-step. A capped, warm-started E-step is a generalised EM step
    # (it raises the likelihood; the next checkpoint continues from here), and bounds the cost.
    estep_max_iter: int = 3
    refactor_every: int = 0       # tracking steps between Cholesky refreshes (0: min(K, max(1, W // 8)))
    min_samples: int = 0          # samples before the first solve (0: max(2n, n + 8) equations' worth)
    sigma_lo: float = 0.05
    sigma_hi: float = 1000.0
    d_lo: float = 1e-9            # d bounds as fractions of the truncation bound a (batch.DEFAULT_D_BOUNDS)
    d_hi: float = 1.0
    a_factor: float = 1.5
    a: float = -1.0               # fixed truncation bound (> 0), or -1 for a_factor * max|e|
    estep_gtol: float = 1e-7
    fp_tol: float = 1e-12
    sigma_start: float = 20.0     # bandwidth after a restart (the paper's EM start)
    # Weak prior on sigma, nats per e-fold (kernels/estep.py): the stream's capped E-step would
    # otherwise wander along the likelihood's flat Gaussian ridge. 0 is the paper's ML.
    sigma_pull: float = 0.05

    def __post_init__(self):
        # Normalise to plain int/float (json-serialisable for save(); a float window would
        # otherwise be truncated into the int config array while the object reports the float).
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type == "int":
                try:
                    if isinstance(v, (bool, np.bool_)):
                        raise TypeError
                    v = operator.index(v)
                except TypeError:
                    raise MKCInputError(f"{f.name} must be an integer; got {v!r}") from None
                if not -C_INT_MAX <= v <= C_INT_MAX:      # the C port's config fields are int
                    raise MKCInputError(f"{f.name} {v} is outside the supported range (|{f.name}| <= {C_INT_MAX})")
            else:
                try:
                    v = float(v)
                except (TypeError, ValueError):
                    raise MKCInputError(f"{f.name} must be a number; got {v!r}") from None
            object.__setattr__(self, f.name, v)
        if self.n < 1 or self.m < 1:
            raise MKCInputError("n and m must be >= 1")
        if self.window < max(2, self.n):
            raise MKCInputError(f"window {self.window} must hold at least n = {self.n} samples")
        if self.window > MAX_WINDOW:
            raise MKCInputError(f"window {self.window} is larger than the largest supported, {MAX_WINDOW} samples")
        nbytes = state_nbytes(self.n, self.m, self.window)
        if nbytes > MAX_STATE_BYTES:
            raise MKCInputError(f"a state for n={self.n}, m={self.m}, window={self.window} would take "
                                f"{nbytes / 2**20:.0f} MiB (> {MAX_STATE_BYTES // 2**20} MiB)")
        if self.estep_every < 1:
            raise MKCInputError("estep_every must be >= 1")
        if self.fp_rounds < 1:
            # 0 would leave A, b weighted by the previous kernel after every E-step (the C port
            # accepts it, but no stream wants it)
            raise MKCInputError(f"fp_rounds must be >= 1; got {self.fp_rounds}")
        for name in ("estep_max_iter", "refactor_every", "min_samples"):
            if getattr(self, name) < 0:
                raise MKCInputError(f"{name} must be >= 0; got {getattr(self, name)}")
        for name in ("sigma_lo", "sigma_hi", "d_lo", "d_hi", "a_factor", "a", "estep_gtol", "fp_tol", "sigma_start",
                     "sigma_pull"):
            if not math.isfinite(getattr(self, name)):
                raise MKCInputError(f"{name} must be a finite number; got {getattr(self, name)}")
        if not (self.sigma_pull >= 0 and np.isfinite(self.sigma_pull)):
            raise MKCInputError(f"sigma_pull must be a finite number >= 0; got {self.sigma_pull}")
        if not (0 < self.sigma_lo < self.sigma_hi) or not (0 < self.d_lo < self.d_hi):
            raise MKCInputError("bounds must satisfy 0 < lo < hi")
        for name in ("a_factor", "sigma_start"):
            if not getattr(self, name) > 0:
                raise MKCInputError(f"{name} must be > 0; got {getattr(self, name)}")
        for name in ("estep_gtol", "fp_tol"):
            if not getattr(self, name) >= 0:
                raise MKCInputError(f"{name} must be >= 0; got {getattr(self, name)}")

    @property
    def effective_min_samples(self) -> int:
        if self.min_samples > 0:
            return min(self.min_samples, self.window)
        need = -(-max(2 * self.n, self.n + 8) // self.m)      # ceil: equations, not samples
        return min(need, self.window)

    @property
    def effective_refactor_every(self) -> int:
        if self.refactor_every > 0:
            return self.refactor_every
        return min(self.estep_every, max(1, self.window // 8))

    def icfg(self):
        a = np.zeros(K.N_ICFG, dtype=np.int64)
        a[K.I_N], a[K.I_M], a[K.I_W], a[K.I_K] = self.n, self.m, self.window, self.estep_every
        a[K.I_FP_ROUNDS], a[K.I_ES_MAX_ITER], a[K.I_MIN_SAMPLES] = self.fp_rounds, self.estep_max_iter, self.effective_min_samples
        a[K.I_REFACTOR] = self.effective_refactor_every
        return a

    def fcfg(self):
        f = np.zeros(K.N_FCFG)
        f[K.F_SIG_LO], f[K.F_SIG_HI], f[K.F_DLO], f[K.F_DHI] = self.sigma_lo, self.sigma_hi, self.d_lo, self.d_hi
        f[K.F_AFAC], f[K.F_FIXED_A], f[K.F_ES_GTOL], f[K.F_FP_TOL] = self.a_factor, self.a, self.estep_gtol, self.fp_tol
        f[K.F_SIG_START] = self.sigma_start
        f[K.F_SIG_PULL] = self.sigma_pull
        return f

    def to_dict(self):
        return asdict(self)


#: (name, dtype, shape as a function of (n, m, W), meaning). Order = C struct order.
STATE_FIELDS = [
    ("icfg", "int64", lambda n, m, W: (K.N_ICFG,), "integer configuration"),
    ("fcfg", "float64", lambda n, m, W: (K.N_FCFG,), "float configuration"),
    ("X", "float64", lambda n, m, W: (W, m, n), "ring buffer: regressor rows"),
    ("Y", "float64", lambda n, m, W: (W, m), "ring buffer: targets"),
    ("C", "float64", lambda n, m, W: (W, m), "ring buffer: the c = w/d^2 each row added"),
    ("A", "float64", lambda n, m, W: (n, n), "weighted normal matrix (eq. 15)"),
    ("b", "float64", lambda n, m, W: (n,), "weighted normal vector (eq. 15)"),
    ("theta", "float64", lambda n, m, W: (n,), "estimate"),
    ("sigma", "float64", lambda n, m, W: (m,), "kernel bandwidth per channel"),
    ("d", "float64", lambda n, m, W: (m,), "nominal deviation per channel"),
    ("a", "float64", lambda n, m, W: (m,), "truncation bound per channel at the last E-step"),
    ("Hes", "float64", lambda n, m, W: (m, 3), "E-step inverse-Hessian warm start per channel"),
    ("L", "float64", lambda n, m, W: (n, n), "scratch: Cholesky factor"),
    ("D", "float64", lambda n, m, W: (n,), "scratch: equilibration"),
    ("xs", "float64", lambda n, m, W: (n,), "scratch: solution"),
    ("tprev", "float64", lambda n, m, W: (n,), "scratch: previous theta"),
    ("R", "float64", lambda n, m, W: (W, m), "scratch: window residuals"),
    ("ebuf", "float64", lambda n, m, W: (W,), "scratch: one channel's residuals"),
    ("cnt", "int64", lambda n, m, W: (K.N_COUNTERS,), "counters (head, count, seen, rejected, ...)"),
    ("fst", "float64", lambda n, m, W: (K.N_FSTATE,), "float scalars (condition, last E-step objective)"),
]

KERNEL_ARGS = [f[0] for f in STATE_FIELDS]


def allocate(cfg: StreamConfig, sigma0, d0, theta0=None) -> dict:
    st = {}
    for name, dtype, shape, _ in STATE_FIELDS:
        st[name] = np.zeros(shape(cfg.n, cfg.m, cfg.window), dtype=dtype)
    st["icfg"][:] = cfg.icfg()
    st["fcfg"][:] = cfg.fcfg()
    st["sigma"][:] = sigma0
    st["d"][:] = d0
    if theta0 is not None:
        st["theta"][:] = theta0
    st["cnt"][K.C_STATUS] = K.WARMING_UP
    st["fst"][K.S_COND] = np.inf
    return st


def state_nbytes(n, m, W, itemsize=8) -> int:
    """Bytes of the state's arrays for a configuration (itemsize 8: double; 4: float build)."""
    total = 0
    for name, dtype, shape, _ in STATE_FIELDS:
        size = int(np.prod(shape(n, m, W)))
        total += size * (8 if dtype == "int64" else itemsize)
    return total


#: names of the config arrays' entries, for a readable mismatch message
_ICFG_NAMES = {K.I_N: "n", K.I_M: "m", K.I_W: "window", K.I_K: "estep_every", K.I_FP_ROUNDS: "fp_rounds",
               K.I_ES_MAX_ITER: "estep_max_iter", K.I_MIN_SAMPLES: "min_samples (effective)",
               K.I_REFACTOR: "refactor_every (effective)"}
_FCFG_NAMES = {K.F_SIG_LO: "sigma_lo", K.F_SIG_HI: "sigma_hi", K.F_DLO: "d_lo", K.F_DHI: "d_hi",
               K.F_AFAC: "a_factor", K.F_FIXED_A: "a", K.F_ES_GTOL: "estep_gtol", K.F_FP_TOL: "fp_tol",
               K.F_SIG_START: "sigma_start", K.F_SIG_PULL: "sigma_pull"}
#: status codes a state may hold (the kernels' and the stream's)
VALID_STATUS = frozenset(STATUS_TEXT) | {K.WARMING_UP, K.REJECTED}


def checked_state(cfg: StreamConfig, state) -> dict:
    """The arrays of `state` as a dict, after checking that the kernels can run on them for `cfg`.

    The kernels index the window with the state's counters and size their loops by its int
    config, unchecked (as the C port does), so a state from another configuration or with a
    counter out of range would read and write outside the arrays. Checked: every field present
    with its shape and dtype; the config arrays equal cfg's; every counter within the range the
    kernels keep it in; the floats that are finite in any state the kernels produce (the window's
    samples, theta, sigma; d > 0 or -1 for "not set"; no negative weight or truncation bound).
    Raises ValueError naming every problem; nothing is copied, so a caller can check, then copy.
    """
    if not hasattr(state, "keys"):
        raise ValueError(f"a stream state is a dict of arrays; got {type(state).__name__}")
    names = [f[0] for f in STATE_FIELDS]
    missing = [k for k in names if k not in state]
    extra = sorted(str(k) for k in state.keys() if k not in names)
    if missing or extra:
        raise ValueError("state fields do not match: " + "; ".join(
            ([f"missing {missing}"] if missing else []) + ([f"unexpected {extra}"] if extra else [])))
    n, m, W = cfg.n, cfg.m, cfg.window
    out, problems = {}, []
    for name, dtype, shape, _ in STATE_FIELDS:
        try:
            arr = np.asarray(state[name])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"state field {name!r} is not an array: {exc}") from None
        if arr.shape != shape(n, m, W) or arr.dtype != np.dtype(dtype):
            problems.append(f"field {name!r} has shape/dtype {arr.shape}/{arr.dtype}, "
                            f"expected {shape(n, m, W)}/{dtype}")
        out[name] = arr
    if problems:
        raise ValueError("state does not fit this stream: " + "; ".join(problems))

    differ = [f"{_ICFG_NAMES[i]} {int(out['icfg'][i])} in the state, {int(v)} here"
              for i, v in enumerate(cfg.icfg()) if out["icfg"][i] != v]
    differ += [f"{_FCFG_NAMES[i]} {float(out['fcfg'][i])!r} in the state, {float(v)!r} here"
               for i, v in enumerate(cfg.fcfg()) if not out["fcfg"][i] == v]
    if differ:
        raise ValueError("state is from another configuration: " + "; ".join(differ))

    c = [int(v) for v in out["cnt"]]
    head, count, seen = c[K.C_HEAD], c[K.C_COUNT], c[K.C_SEEN]
    if not 0 <= count <= W:
        problems.append(f"window count {count} outside [0, {W}]")
    if not 0 <= head < W:
        problems.append(f"ring-buffer head {head} outside [0, {W - 1}]")
    elif 0 <= count < W and head > count:
        # the head only ever reaches the slot after the last one filled (learn_one)
        problems.append(f"ring-buffer head {head} is past the {count} filled slots")
    if count > seen:
        problems.append(f"window count {count} > samples seen {seen}")
    for k, label in ((K.C_SEEN, "samples seen"), (K.C_REJECTED, "samples rejected"), (K.C_ESTEPS, "E-steps"),
                     (K.C_SINCE, "samples since the E-step"), (K.C_SINGULAR, "singular solves"),
                     (K.C_FP_ITERS, "fixed-point rounds"), (K.C_RESTARTS, "restarts"), (K.C_FACTORS, "factorisations")):
        if c[k] < 0:
            problems.append(f"counter {label} is negative ({c[k]})")
    if c[K.C_STATUS] not in VALID_STATUS:
        problems.append(f"status {c[K.C_STATUS]} is not a status code")
    if not 0 <= c[K.C_LAST_SLOT] < W:
        problems.append(f"last slot {c[K.C_LAST_SLOT]} outside [0, {W - 1}]")
    if not -1 <= c[K.C_FACTOR_AGE] <= cfg.effective_refactor_every:
        problems.append(f"factor age {c[K.C_FACTOR_AGE]} outside [-1, {cfg.effective_refactor_every}]")

    for name in ("X", "Y", "theta", "sigma"):
        if not np.isfinite(out[name]).all():
            problems.append(f"field {name!r} has NaN/inf values")
    if not (out["sigma"] > 0).all():
        problems.append("sigma has values <= 0")
    d = out["d"]
    if not ((d > 0) | (d == -1.0)).all():
        problems.append(f"d has values that are neither > 0 nor -1 (not set): {d.tolist()}")
    for name in ("C", "a"):
        if (out[name] < 0).any():
            problems.append(f"field {name!r} has negative values")
    if problems:
        raise ValueError("state is corrupt: " + "; ".join(problems))
    return out
