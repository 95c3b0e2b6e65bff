"""The streaming estimator's fixed-size state: field for field the C struct of firmware_ref/.

Sizes depend only on the configuration (n parameters, m channels, window W), never on the number
of samples seen. `STATE_FIELDS` is the single source of truth for the layout: the C struct in
firmware_ref/include/mkc.h mirrors it (tests/test_firmware.py checks the field set) and its index
constants are generated from it by tools/gen_firmware_tables.py.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .kernels import window as K

STATE_VERSION = 2


@dataclass(frozen=True)
class StreamConfig:
    n: int                        # parameters (9 for the ellipsoid)
    m: int = 1                    # residual channels
    window: int = 256             # W: samples kept
    estep_every: int = 32         # K: E-step + rebuild every K samples
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
        if self.n < 1 or self.m < 1:
            raise ValueError("n and m must be >= 1")
        if self.window < max(2, self.n):
            raise ValueError(f"window {self.window} must hold at least n = {self.n} samples")
        if self.estep_every < 1:
            raise ValueError("estep_every must be >= 1")
        if not (self.sigma_pull >= 0 and np.isfinite(self.sigma_pull)):
            raise ValueError(f"sigma_pull must be a finite number >= 0; got {self.sigma_pull}")
        if not (0 < self.sigma_lo < self.sigma_hi) or not (0 < self.d_lo < self.d_hi):
            raise ValueError("bounds must satisfy 0 < lo < hi")

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
