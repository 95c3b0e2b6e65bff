"""StreamingMKC: MKC-EM over a sliding window, one sample at a time, in fixed memory.

River-style API: learn_one / learn_many / predict_one / snapshot / reset, and a state that saves
and restores bit-exactly (a restart resumes where it stopped). The work is done by the jitted
kernels in kernels/window.py; this class validates shapes and holds the arrays.
"""
from __future__ import annotations

import json
import operator
import struct
import zipfile
import zlib
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np

from ._validation import per_channel
from .batch import DEFAULT_SIGMA_START
from .kernels import STATUS_TEXT
from .kernels import window as K
from .defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from .state import KERNEL_ARGS, STATE_VERSION, StreamConfig, allocate, checked_state, state_nbytes

#: what reading a damaged .npz raises (zipfile and numpy's format parser), besides OSError for a
#: file that cannot be opened at all
_ARCHIVE_ERRORS = (ValueError, KeyError, TypeError, EOFError, OverflowError, NotImplementedError, struct.error,
                   zlib.error, zipfile.BadZipFile)

#: the counters' names (the "cnt" state array), in kernels/window.py's order
_COUNTER_INDEX = {name: getattr(K, "C_" + name.upper()) for name in (
    "head", "count", "seen", "rejected", "esteps", "since", "status", "singular", "fp_iters", "last_slot",
    "restarts", "factor_age", "factors")}

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

    def __init__(self, n, m=1, window=DEFAULT_WINDOW, estep_every=DEFAULT_ESTEP_EVERY, sigma=None, d=None, theta0=None,
                 **config):
        self.config = StreamConfig(n=n, m=m, window=window, estep_every=estep_every, **config)
        m, n = self.config.m, self.config.n
        # finite and > 0 per channel, as the C port's init requires (a NaN sigma ran silently singular)
        self._sigma0 = per_channel(DEFAULT_SIGMA_START if sigma is None else sigma, m, "sigma").copy()
        self._d0 = np.full(m, -1.0) if d is None else per_channel(d, m, "d").copy()
        if sigma is not None and "sigma_start" not in config:
            self.config = replace(self.config, sigma_start=float(np.max(self._sigma0)))
        self._theta0 = None
        if theta0 is not None:
            self._theta0 = np.array(theta0, dtype=np.float64).ravel()
            if self._theta0.shape != (n,) or not np.isfinite(self._theta0).all():
                raise ValueError(f"theta0 must be {n} finite numbers; got shape {np.shape(theta0)}")
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
        """Restore a state from `state` (bit-exact). It must come from a stream of the same
        configuration and be intact; otherwise ValueError, and this stream is left unchanged."""
        checked = checked_state(self.config, state)      # everything first: a failed load changes nothing
        for k, v in self._st.items():
            v[...] = checked[k]
        return self

    def save(self, path_or_file):
        meta = json.dumps({"version": STATE_VERSION, "config": self.config.to_dict(),
                           "sigma0": self._sigma0.tolist(), "d0": self._d0.tolist()})
        np.savez(path_or_file, __meta__=np.frombuffer(meta.encode(), dtype=np.uint8), **self._st)

    @classmethod
    def load(cls, path_or_file):
        """A stream from a file written by save(). ValueError for a file that is not an intact state
        file (truncated, corrupt, another version or configuration); OSError only when it cannot be opened."""
        try:
            z = np.load(path_or_file, allow_pickle=False)
        except _ARCHIVE_ERRORS as exc:
            raise ValueError(f"not a stream state file: {type(exc).__name__}: {exc}") from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError("not a stream state file: a single array, not an .npz archive")
        with z:
            try:
                meta = json.loads(bytes(z["__meta__"]).decode())
                if not isinstance(meta, dict) or meta.get("version") != STATE_VERSION:
                    version = meta.get("version") if isinstance(meta, dict) else None
                    raise ValueError(f"state file version {version} != {STATE_VERSION}")
                cfg = dict(meta["config"])
                n, m, W, Kk = cfg.pop("n"), cfg.pop("m"), cfg.pop("window"), cfg.pop("estep_every")
                d0 = np.asarray(meta["d0"], dtype=np.float64)
                obj = cls(n, m, W, Kk, sigma=meta["sigma0"], d=None if d0.size and d0.flat[0] <= 0 else d0, **cfg)
                state = {k: z[k] for k in z.files if k != "__meta__"}
            except _ARCHIVE_ERRORS as exc:
                # a missing member or meta key, a wrong meta type, a damaged or truncated member
                raise ValueError(f"not a usable stream state file: {type(exc).__name__}: {exc}") from None
        return obj.load_state(state)

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
        """Feed one sample; returns the kernel status code (see STREAM_STATUS_TEXT).

        slot: -1 (default) writes at the ring buffer's head; 0 <= slot < window replaces the sample
        in that slot, or (slot == the window count) fills the next free one.
        """
        xk, yk = self._shape_one(x, y)
        if slot != -1:
            slot = self._check_slot(slot)
        return K.learn_one(*self._args, xk, yk, slot)

    def _check_slot(self, slot) -> int:
        # the C port's rule (stream.c): the kernel indexes the window with it, unchecked
        try:
            if isinstance(slot, (bool, np.bool_)):
                raise TypeError
            slot = operator.index(slot)
        except TypeError:
            raise TypeError(f"slot must be an integer; got {slot!r}") from None
        count, W = int(self._st["cnt"][K.C_COUNT]), self.config.window
        if not (slot == -1 or 0 <= slot < W and slot <= count):
            allowed = ("-1 (the ring buffer's head)" + (f", 0..{count - 1} (a filled slot to replace)" if count else "")
                       + (f", {count} (the next free slot)" if count < W else ""))
            raise ValueError(f"slot {slot} is outside the window of {W} samples ({count} filled): expected {allowed}")
        return slot

    def learn_many(self, X, Y) -> np.ndarray:
        """Feed samples X (T, m, n) or (T, n), Y (T, m) or (T,); returns per-sample status (T,)."""
        n, m = self.config.n, self.config.m
        X = np.ascontiguousarray(X, dtype=np.float64)
        Y = np.ascontiguousarray(Y, dtype=np.float64)
        if X.size % (m * n) or Y.size % m:
            raise ValueError(f"expected X (T, {m}, {n}) and Y (T, {m}); got X{X.shape}, Y{Y.shape}")
        X = X.reshape(-1, m, n)
        Y = Y.reshape(-1, m)
        if X.shape[0] != Y.shape[0]:
            raise ValueError(f"X has {X.shape[0]} samples, Y has {Y.shape[0]}")
        status = np.empty(X.shape[0], dtype=np.int8)
        K.learn_many(*self._args, X, Y, status)
        return status

    def predict_one(self, x):
        n, m = self.config.n, self.config.m
        return np.asarray(x, dtype=np.float64).reshape(m, n) @ self._st["theta"]

    # -- inspection ------------------------------------------------------------------------
    # The scalars and the per-channel vectors are returned as copies (a few numbers: a value
    # that stays as it was when read, like snapshot()); the window arrays through view(), a
    # read-only view (no copy of W x m x n values, but it follows the stream as it learns).
    @property
    def theta(self):
        return self._st["theta"].copy()

    @property
    def sigma(self) -> np.ndarray:
        """Kernel bandwidth per channel (a copy)."""
        return self._st["sigma"].copy()

    @property
    def d(self) -> np.ndarray:
        """Nominal deviation per channel (a copy)."""
        return self._st["d"].copy()

    @property
    def a(self) -> np.ndarray:
        """Truncation bound per channel at the last E-step (a copy)."""
        return self._st["a"].copy()

    @property
    def counters(self) -> dict:
        """Every counter by name (head, count, seen, rejected, esteps, since, status, singular,
        fp_iters, last_slot, restarts, factor_age, factors), as ints."""
        c = self._st["cnt"]
        return {name: int(c[i]) for name, i in _COUNTER_INDEX.items()}

    @property
    def samples_seen(self) -> int:
        return int(self._st["cnt"][K.C_SEEN])

    @property
    def samples_rejected(self) -> int:
        return int(self._st["cnt"][K.C_REJECTED])

    @property
    def window_count(self) -> int:
        """Samples in the window."""
        return int(self._st["cnt"][K.C_COUNT])

    @property
    def esteps(self) -> int:
        return int(self._st["cnt"][K.C_ESTEPS])

    @property
    def restarts(self) -> int:
        return int(self._st["cnt"][K.C_RESTARTS])

    @property
    def status(self) -> str:
        """The last kernel status as text (STREAM_STATUS_TEXT)."""
        code = int(self._st["cnt"][K.C_STATUS])
        return STREAM_STATUS_TEXT.get(code, str(code))

    @property
    def status_code(self) -> int:
        """The last kernel status code (text: STREAM_STATUS_TEXT, or snapshot().status)."""
        return int(self._st["cnt"][K.C_STATUS])

    def view(self, name: str) -> np.ndarray:
        """A read-only view of one state array (a name of state.STATE_FIELDS: "X", "Y", "C", "A",
        "b", "theta", "Hes", "cnt", ...). No copy, so it follows the stream; copy it to keep a value."""
        v = self._st[name].view()
        v.flags.writeable = False
        return v

    def views(self) -> dict:
        """Every state array by name as a read-only view (see view())."""
        return {k: self.view(k) for k in self._st}

    @property
    def kernel_state(self):
        """The live state arrays by name, writable (a read-only mapping of shared arrays). For code
        that runs the window kernels on this stream (MagCalibrator); anything else: view()."""
        return MappingProxyType(self._st)

    @property
    def kernel_args(self) -> tuple:
        """The live state arrays in the window kernels' argument order (state.KERNEL_ARGS)."""
        return self._args

    def count_rejected(self, n: int) -> None:
        """Count n samples rejected before they reached the stream (e.g. non-finite ones held back)."""
        self._st["cnt"][K.C_REJECTED] += int(n)

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

