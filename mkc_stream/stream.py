"""StreamingMKC: MKC-EM over a sliding window, one sample at a time, in fixed memory.

River-style API: learn_one / learn_many / predict_one / snapshot / reset, and a state that saves
and restores bit-exactly (a restart resumes where it stopped). The work is done by the jitted
kernels in kernels/window.py; this class validates shapes and holds the arrays.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from .batch import DEFAULT_SIGMA_START
from .kernels import STATUS_TEXT
from .kernels import window as K
from .state import KERNEL_ARGS, STATE_VERSION, StreamConfig, allocate, state_nbytes

STREAM_STATUS_TEXT = dict(STATUS_TEXT)
STREAM_STATUS_TEXT.update({K.WARMING_UP: "warming up", K.REJECTED: "sample rejected (NaN/inf)"})


@dataclass(frozen=True)
class StreamSnapshot:
    """A frozen copy of the estimate."""

    theta: np.ndarray
    sigma: np.ndarray
    d: np.ndarray
    samples_seen: int
    samples_rejected: int
    window_count: int
    esteps: int
    status: str
    condition: float

    def to_dict(self):
        return {"theta": self.theta.tolist(), "sigma": self.sigma.tolist(), "d": self.d.tolist(),
                "samples_seen": self.samples_seen, "samples_rejected": self.samples_rejected,
                "window_count": self.window_count, "esteps": self.esteps, "status": self.status,
                "condition": self.condition}


class StreamingMKC:
    """Streaming MKC-EM for y_k = X_k theta + v_k with X_k (m, n).

    Parameters: n, m; window W (samples kept), estep_every K; sigma (start, per channel or
    scalar, default 20 as in the paper), d (start; None: RMS of the first WLS residuals);
    other StreamConfig fields as keywords (fp_rounds, estep_max_iter, min_samples, a_factor, ...).
    """

    def __init__(self, n, m=1, window=256, estep_every=32, sigma=None, d=None, theta0=None, **config):
        if sigma is not None and "sigma_start" not in config:
            config["sigma_start"] = float(np.max(sigma))
        self.config = StreamConfig(n=n, m=m, window=window, estep_every=estep_every, **config)
        self._sigma0 = np.broadcast_to(np.asarray(DEFAULT_SIGMA_START if sigma is None else sigma, float), (m,)).copy()
        self._d0 = np.broadcast_to(np.asarray(-1.0 if d is None else d, float), (m,)).copy()
        if np.any(self._sigma0 <= 0) or (d is not None and np.any(self._d0 <= 0)):
            raise ValueError("sigma and d must be > 0")
        self._theta0 = None if theta0 is None else np.asarray(theta0, float).copy()
        self.reset()

    # -- state -----------------------------------------------------------------------------
    def reset(self):
        self._st = allocate(self.config, self._sigma0, self._d0, self._theta0)
        self._args = tuple(self._st[k] for k in KERNEL_ARGS)
        return self

    @property
    def state(self) -> dict:
        """A copy of every state array (bit-exact); restore with load_state()."""
        return {k: v.copy() for k, v in self._st.items()}

    def load_state(self, state: dict):
        for k, v in self._st.items():
            src = np.asarray(state[k])
            if src.shape != v.shape or src.dtype != v.dtype:
                raise ValueError(f"state field {k!r} has shape/dtype {src.shape}/{src.dtype}, expected {v.shape}/{v.dtype}")
            v[...] = src
        return self

    def save(self, path_or_file):
        meta = json.dumps({"version": STATE_VERSION, "config": self.config.to_dict(),
                           "sigma0": self._sigma0.tolist(), "d0": self._d0.tolist()})
        np.savez(path_or_file, __meta__=np.frombuffer(meta.encode(), dtype=np.uint8), **self._st)

    @classmethod
    def load(cls, path_or_file):
        with np.load(path_or_file) as z:
            meta = json.loads(bytes(z["__meta__"]).decode())
            if meta.get("version") != STATE_VERSION:
                raise ValueError(f"state file version {meta.get('version')} != {STATE_VERSION}")
            cfg = dict(meta["config"])
            n, m, W, Kk = cfg.pop("n"), cfg.pop("m"), cfg.pop("window"), cfg.pop("estep_every")
            obj = cls(n, m, W, Kk, sigma=meta["sigma0"], d=None if meta["d0"][0] <= 0 else meta["d0"], **cfg)
            obj.load_state({k: z[k] for k in obj._st})
        return obj

    def nbytes(self) -> int:
        return state_nbytes(self.config.n, self.config.m, self.config.window)

    # -- learning --------------------------------------------------------------------------
    def _shape_one(self, x, y):
        n, m = self.config.n, self.config.m
        if (type(x) is np.ndarray and type(y) is np.ndarray and x.dtype == np.float64 and y.dtype == np.float64
                and x.shape == (m, n) and y.shape == (m,)):
            return x, y               # the per-sample fast path: no conversion, no copy
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if x.size != m * n or y.size != m:
            raise ValueError(f"expected x of {m}x{n} and y of {m} values; got x{x.shape}, y{y.shape}")
        return x.reshape(m, n), y.reshape(m)

    def learn_one(self, x, y, slot=-1) -> int:
        """Feed one sample; returns the kernel status code (see STREAM_STATUS_TEXT)."""
        xk, yk = self._shape_one(x, y)
        return K.learn_one(*self._args, xk, yk, slot)

    def learn_many(self, X, Y) -> np.ndarray:
        """Feed samples X (T, m, n) or (T, n), Y (T, m) or (T,); returns per-sample status (T,)."""
        n, m = self.config.n, self.config.m
        X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, m, n)
        Y = np.ascontiguousarray(Y, dtype=np.float64).reshape(-1, m)
        if X.shape[0] != Y.shape[0]:
            raise ValueError(f"X has {X.shape[0]} samples, Y has {Y.shape[0]}")
        status = np.empty(X.shape[0], dtype=np.int8)
        K.learn_many(*self._args, X, Y, status)
        return status

    def predict_one(self, x):
        n, m = self.config.n, self.config.m
        return np.asarray(x, dtype=np.float64).reshape(m, n) @ self._st["theta"]

    # -- inspection ------------------------------------------------------------------------
    @property
    def theta(self):
        return self._st["theta"].copy()

    def snapshot(self) -> StreamSnapshot:
        c = self._st["cnt"]
        return StreamSnapshot(theta=self._st["theta"].copy(), sigma=self._st["sigma"].copy(), d=self._st["d"].copy(),
                              samples_seen=int(c[K.C_SEEN]), samples_rejected=int(c[K.C_REJECTED]),
                              window_count=int(c[K.C_COUNT]), esteps=int(c[K.C_ESTEPS]),
                              status=STREAM_STATUS_TEXT.get(int(c[K.C_STATUS]), str(int(c[K.C_STATUS]))),
                              condition=float(self._st["fst"][K.S_COND]))

    def window(self):
        """(X, Y, C) of the samples in the window, oldest first (for a ring buffer)."""
        c = self._st["cnt"]
        count, head, W = int(c[K.C_COUNT]), int(c[K.C_HEAD]), self.config.window
        idx = np.arange(count) if count < W else (head + np.arange(W)) % W
        return self._st["X"][idx].copy(), self._st["Y"][idx].copy(), self._st["C"][idx].copy()

    def weights(self):
        """Kernel weights w = c d^2 of the window's samples (oldest first), shape (count, m)."""
        X, Y, C = self.window()
        return C * self._st["d"] ** 2

    def __repr__(self):
        s = self.snapshot()
        return (f"StreamingMKC(n={self.config.n}, m={self.config.m}, window={self.config.window}, "
                f"K={self.config.estep_every}; seen={s.samples_seen}, esteps={s.esteps}, status={s.status!r})")

