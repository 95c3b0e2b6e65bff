"""The magnetometer's timing against the gyroscope: a latency test that the accelerometer's
noise does not limit.

A constant field seen by a rotating sensor obeys dB/dt = -w x B (sensor frame, B the calibrated
field, w the angular rate). A magnetometer sampled late by delta reads B(t - delta), so

    r(t) = dB/dt + w(t) x B(t) = (w(t) - w(t - delta)) x B(t) ~ delta (dw/dt x B)    (to first order)

The dip channel sees the same delay through the accelerometer, whose linear accelerations (a few
degrees, correlated over ~0.5 s) swamp a few milliseconds. The gyroscope's noise is two orders of
magnitude smaller: on the blind benchmark's 20 Hz figure-8 flights a 5.4 ms delay gives t ~ 100
here against t 2.2 in the dip channel.

What else makes r non-zero is fitted alongside (nuisance columns, all linear):
* the gyroscope's calibration against the magnetometer's frame: w_true = K w + b_g (K: scale,
  cross-axis and any axis convention or unit, 9; b_g: bias, 3). K is fitted first on dB/dt
  alone, so a gyroscope in deg/s or with swapped axes still gives the delay in seconds;
* what the baseline calibration leaves: a hard-iron error in the calibrated frame (3) and a
  symmetric soft-iron error (6; its isotropic part is invisible to a rotation).
A hysteresis (the magnetisation lagging the field) also looks like a delay here: this test says
"the magnetometer lags the rotation", the diagnosis says by which effect.

Standard errors are block sums over the recording's time blocks (autocorrelation and
heteroscedasticity), read on a Student-t with blocks - 1 degrees of freedom. The derivatives are
central differences on the actual time stamps; the residual is reweighted (4 robust sd) so
disturbance bursts do not carry the fit.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from ..robust import mad_sd

#: robust cut of the reweighted least squares (robust standard deviations)
CUT = 4.0
#: the sensor must turn: median angular rate (rad/s, after K) below this is "not testable"
MIN_RATE = 0.05
#: at least this many usable time blocks for the block-sum standard error
MIN_BLOCKS = 8
#: the sensor must turn little between samples: above this median rotation per sample (rad) the
#: test is "not testable". The central differences' truncation error is about phi^2 / 6 of the
#: derivative (phi the rotation per sample), and on a figure-8 (a periodic motion, read at the
#: same phases every figure) its part along the delay column does not average out: a null of
#: 2 x 10^4 samples read a delay of 0.015 ms (t 0.4) at 0.11 rad per sample, 0.06 ms (t 1.8) at
#: 0.23, 0.52 ms (t 7.9) at 0.61 and 1.98 ms (t 36) at 0.84 (10^6 samples at 50 Hz decimated
#: by 50: one sample a second)
MAX_STEP_RAD = 0.2

_E3 = np.eye(3)


def _gyro_columns(w, B):
    """d r / d (K_ij, b_k) for r = dB/dt + (K w + b) x B: (e_i w_j) x B, then e_k x B."""
    out = []
    for i in range(3):
        for j in range(3):
            a = np.zeros_like(w)
            a[:, i] = w[:, j]
            out.append(np.cross(a, B))
    return out + [np.cross(np.broadcast_to(_E3[k], B.shape), B) for k in range(3)]


def _nuisance(w, B):
    cols = _gyro_columns(w, B)                                               # K - I, gyro bias
    cols += [np.cross(w, np.broadcast_to(_E3[k], B.shape)) for k in range(3)]  # hard-iron error
    wxB = np.cross(w, B)
    for i in range(3):                                                       # soft-iron error E
        for j in range(i, 3):
            E = np.zeros((3, 3))
            E[i, j] = E[j, i] = 1.0
            cols.append(np.cross(w, B @ E) - wxB @ E)
    return cols


def _robust_lsq(X, y, ok):
    """Reweighted least squares on rows ok: (theta, weights, pinv of the weighted Gram)."""
    wt = ok.astype(float)
    for _ in range(3):
        A = (X * wt[:, None]).T @ X
        Ai = np.linalg.pinv(A, rcond=1e-10)
        th = Ai @ ((X * wt[:, None]).T @ y)
        e = y - X @ th
        s = mad_sd(e[wt > 0], 0.0)
        wt = (ok & (np.abs(e) < CUT * s)).astype(float)
    A = (X * wt[:, None]).T @ X
    Ai = np.linalg.pinv(A, rcond=1e-10)
    return Ai @ ((X * wt[:, None]).T @ y), wt, Ai


def gyro_delay(frame, state, valid=None) -> dict:
    """The magnetometer's delay against the gyroscope (ms, > 0: the magnetometer is late).

    frame: the diagnosis frame (t, m, gyro, block); state: the calibration (b, S);
    valid: (N,) samples to use (default all). Returns {"testable": False, "reason": ...} or
    {"testable": True, "delay_ms", "se_ms", "t", "p" (two-sided), "dof", "samples",
    "rate_rad_s", "gyro_matrix"}.
    """
    if frame.gyro is None:
        return {"testable": False, "reason": "no gyroscope columns"}
    t = frame.t
    B = (frame.m - state.b) @ np.asarray(state.S).T
    w_raw = np.asarray(frame.gyro, dtype=float)
    ok = np.ones(frame.n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool).copy()
    ok &= np.all(np.isfinite(w_raw), axis=1) & np.all(np.isfinite(B), axis=1)
    # a central difference needs both neighbours
    ok[1:-1] &= ok[:-2] & ok[2:]
    ok[[0, -1]] = False
    if ok.sum() < 100:
        return {"testable": False, "reason": f"only {int(ok.sum())} usable samples"}
    w0 = np.where(np.isfinite(w_raw), w_raw, 0.0)
    B0 = np.where(np.isfinite(B), B, 0.0)
    Bd = np.gradient(B0, t, axis=0)
    okr = np.repeat(ok, 3)

    # 1. the gyroscope's calibration against the magnetometer: dB/dt = -(K w + b) x B
    X1 = np.stack(_gyro_columns(w0, B0), axis=2).reshape(-1, 12)
    th1, _, _ = _robust_lsq(X1, -Bd.reshape(-1), okr)
    K, b = th1[:9].reshape(3, 3), th1[9:]
    sv = np.linalg.svd(K, compute_uv=False)
    if not (np.all(np.isfinite(sv)) and sv[-1] > 0.2 * sv[0]):
        return {"testable": False, "reason": "the gyroscope does not follow the magnetometer's rotation "
                                             f"(singular values of its fitted matrix {np.round(sv, 3).tolist()})"}
    w = w0 @ K.T + b
    rate = float(np.median(np.linalg.norm(w[ok], axis=1)))
    if rate < MIN_RATE:
        return {"testable": False, "reason": f"the sensor hardly turns (median rate {rate:.3f} rad/s)"}
    step = rate * frame.dt0
    if step > MAX_STEP_RAD:
        dec = getattr(frame, "decimation", 1)
        return {"testable": False, "reason": f"the sensor turns {step:.2f} rad between samples (median; the "
                                             f"derivatives need at most {MAX_STEP_RAD})"
                                             + (f"; the recording was decimated by {dec}" if dec > 1 else "")}

    # 2. the delay, with the calibration's leftovers as nuisance
    r = Bd + np.cross(w, B0)
    wd = np.gradient(w, t, axis=0)
    X = np.stack([np.cross(wd, B0) * 1e-3] + _nuisance(w, B0), axis=2)      # delay column per ms
    k = X.shape[2]
    X = X.reshape(-1, k)
    th, wt, Ai = _robust_lsq(X, r.reshape(-1), okr)
    e = (r.reshape(-1) - X @ th) * wt
    blk = np.repeat(frame.block, 3)
    used = np.unique(blk[wt > 0])
    if used.size < MIN_BLOCKS:
        return {"testable": False, "reason": f"only {used.size} time blocks with usable samples"}
    g = np.zeros((frame.n_blocks, k))
    np.add.at(g, blk, X * e[:, None])
    g = g[used]
    nb = used.size
    V = Ai @ (g.T @ g) @ Ai * nb / (nb - 1)
    se = float(np.sqrt(max(V[0, 0], 0.0)))
    if not (se > 0 and np.isfinite(th[0])):
        return {"testable": False, "reason": "the rotation does not excite a delay (no angular acceleration)"}
    tval = float(th[0] / se)
    fold = np.repeat(np.asarray(frame.block) % 2 == 0, 3)
    return {"testable": True, "delay_ms": float(th[0]), "se_ms": se, "t": tval,
            "p": float(2.0 * stats.t.sf(abs(tval), nb - 1)), "dof": int(nb - 1),
            "samples": int(ok.sum()), "rate_rad_s": rate, "gyro_matrix": K.tolist(),
            "held_out_drop": _held_out_drop(X, r.reshape(-1), okr, fold)}


def _held_out_drop(X, y, ok, fold):
    """How much the delay lowers the timing residual on blocks its fit did not see: fitted with
    and without the delay column on the even blocks and scored on the odd ones, and the other
    way round; sum of min((e / s)^2, 16) without minus with (s: the robust scale of the
    residual without the delay), > 0 when the delay predicts held-out blocks."""
    drop = 0.0
    for f in (fold, ~fold):
        test = ok & ~f
        if not (ok & f).any() or not test.any():
            return float("nan")
        th1, _, _ = _robust_lsq(X, y, ok & f)
        th0, _, _ = _robust_lsq(X[:, 1:], y, ok & f)
        e1, e0 = y[test] - X[test] @ th1, y[test] - X[test][:, 1:] @ th0
        s = mad_sd(e0, 0.0)
        if not s > 0:
            return float("nan")
        drop += float(np.sum(np.minimum((e0 / s) ** 2, 16.0)) - np.sum(np.minimum((e1 / s) ** 2, 16.0)))
    return drop
