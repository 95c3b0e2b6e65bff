"""What the batch solvers give at a streaming checkpoint: the reference the stream must equal.

Used by the stream's tests and the long-run study (tools/long_run.py). Pure Python beside
stream.py and batch.py: it does not touch the C port, whose cross-check (cport/compare.py) compares
the port with the stream itself.

At a checkpoint the stream runs, on the samples its window holds, one warm-started E-step
(Algorithm 2) per channel and then fp_rounds fixed-point rounds (Algorithm 1) from the theta it
had before the checkpoint sample. `batch_checkpoint` runs the batch kernels on the same window from the same
warm start; `capture` records that warm start.
"""
from __future__ import annotations

import numpy as np

from .batch import wls_solve
from .kernels import window as K
from .kernels.correntropy import residuals
from .kernels.estep import estep_channel
from .kernels.mstep import mstep_fixed_point


def capture(est) -> dict:
    """The stream's warm start, taken just before feeding a sample."""
    st = est.views()
    return {"theta": st["theta"].copy(), "sigma": st["sigma"].copy(), "d": st["d"].copy(),
            "Hes": st["Hes"].copy(), "a": st["a"].copy(), "esteps": int(st["cnt"][K.C_ESTEPS])}


def batch_checkpoint(est, pre):
    """(theta, sigma, d) of the batch solvers on est's window from the warm start `pre`."""
    st = est.views()
    cfg = est.config
    count = int(st["cnt"][K.C_COUNT])
    X, Y = st["X"][:count].copy(), st["Y"][:count].copy()      # (writable, as the kernels' signatures)
    theta = pre["theta"].copy()
    sigma, d, H = pre["sigma"].copy(), pre["d"].copy(), pre["Hes"].copy()
    N, m, n = X.shape
    ws = [np.empty((N, m)), np.empty((N, m)), np.empty((n, n)), np.empty(n), np.empty(n), np.zeros((n, n)), np.empty(n)]
    if pre["esteps"] == 0:   # initialisation: WLS, then Algorithm 1 at the start (sigma, d)
        theta, _ = wls_solve(X, Y, d)
        mstep_fixed_point(X, Y, sigma, d, theta, cfg.fp_rounds, cfg.fp_tol, *ws)
    R = np.empty((N, m))
    residuals(X, Y, theta, R)        # the kernels' own loop order: bitwise the stream's residuals
    for i in range(m):
        a = max(cfg.a_factor * np.abs(R[:, i]).max(), 1e-12 * (1.0 + np.abs(Y[:, i]).max())) if cfg.a <= 0 else cfg.a
        if not (0.5 * pre["a"][i] <= a <= 2.0 * pre["a"][i]):
            H[i] = 0.0               # the stream forgets the curvature when a moves by > 2x
            if pre["a"][i] > 0.0 and a > 2.0 * pre["a"][i] and sigma[i] > K.START_SIGMA_ROBUST:
                sigma[i] = K.START_SIGMA_ROBUST   # ... and restarts sigma on the robust side after a burst
        s, dd, F, its, stt = estep_channel(R[:, i].copy(), count, a, sigma[i], d[i], cfg.sigma_lo, cfg.sigma_hi,
                                           cfg.d_lo * a, cfg.d_hi * a, cfg.estep_max_iter, cfg.estep_gtol, cfg.sigma_pull, H[i])
        sigma[i], d[i] = s, dd
    mstep_fixed_point(X, Y, sigma, d, theta, cfg.fp_rounds, cfg.fp_tol, *ws)
    return theta, sigma, d


def accumulation_drift(est) -> float:
    """max |A - A_rebuilt| / max |A|: how far the add/remove updates have drifted from the buffer."""
    st = est.views()
    count = int(st["cnt"][K.C_COUNT])
    X, C = st["X"][:count], st["C"][:count]
    A = np.einsum("kmi,km,kmj->ij", X, C, X)
    return float(np.abs(np.tril(st["A"]) - np.tril(A)).max() / max(np.abs(A).max(), 1e-300))
