"""Residual channels of a calibration and the joint (calibration + effects) Gauss-Newton fit.

Channels (the observables a calibration leaves):

* ``norm``: |S (m - b)| - F, in the recording's magnetometer unit. Its Jacobian with respect
  to a perturbation dm of the raw sample is v^T S (v the calibrated direction).
* ``dip`` (with an accelerometer): the angle between the calibrated field and the accelerometer
  minus its fitted constant dip0, in rad; Jacobian -(g - (v.g) v)^T S / (|m_cal| sin(dip)).

Every model is "baseline + mean effects": the baseline's 9 calibration parameters (b: 3, a
symmetric perturbation of S: 6), dip0, and each effect's parameters, whose contribution to the
raw signal is G(t) theta (G from :mod:`forms`). All of them enter the channels through the
same Jacobian, so one weighted least-squares step fits them jointly; a few Gauss-Newton
iterations (re-linearising at the new b, S, theta) remove the linearisation error of large
effects. The columns are read at :func:`noise_free_point`, not at the noisy samples: the fit
then solves X' W e = 0 with columns that share no noise with the residual (an instrumental-
variable fit); read at the samples, they fitted a cubic term to the noise alone (on 12
hand-waved nulls with 0.6 uT of white noise, 10^4 samples: +0.74 uT at 50 uT on x, 0.08 uT
standard error). Weights are hard: a sample counts while |e| < 4 sigma of its channel (the
same rule decides "down-weighted" in the statistics panel and in the replicas).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

INLIER_K = 4.0
#: relative ridge of every solve (times the normal matrix's mean diagonal, which the
#: calibration's columns dominate): a form's columns must stand well above it
RIDGE = 1e-10
_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: rad: the widest angle between a sample's two neighbours whose average still stands for the
#: sample in :func:`noise_free_point` (at 0.3 rad the average's error across the field is at most
#: 0.15 F and, for motion that is smooth over three samples, a small share of that)
NEIGHBOUR_SPREAD_RAD = 0.3
#: and the least distance between them, in robust sds of the norm residual (their difference has
#: sd sqrt(2) sigma per axis: 6 sigma is exceeded by noise alone with probability 4e-4)
NEIGHBOUR_NOISE_K = 6.0


@dataclass
class State:
    b: np.ndarray
    S: np.ndarray
    F: float
    dip0: float = 0.0

    def copy(self):
        return State(self.b.copy(), self.S.copy(), float(self.F), float(self.dip0))


@dataclass
class Channels:
    r: np.ndarray            # (N, C)
    J: np.ndarray            # (N, C, 3)
    mc: np.ndarray           # (N, 3) calibrated field
    rho: np.ndarray          # (N,)
    v: np.ndarray            # (N, 3) calibrated direction


def n_channels(frame) -> int:
    return 2 if frame.acc_unit is not None else 1


def channels(m, frame, st: State) -> Channels:
    mc = (m - st.b) @ st.S.T
    rho = np.linalg.norm(mc, axis=1)
    v = mc / rho[:, None]
    C = n_channels(frame)
    r = np.empty((m.shape[0], C))
    J = np.empty((m.shape[0], C, 3))
    r[:, 0] = rho - st.F
    J[:, 0] = v @ st.S
    if C == 2:
        g = np.nan_to_num(frame.acc_unit)
        c = np.clip(np.sum(v * g, axis=1), -1.0, 1.0)
        th = np.arccos(c)
        s = np.maximum(np.sqrt(1.0 - c * c), 1e-6)
        r[:, 1] = th - st.dip0
        J[:, 1] = -((g - c[:, None] * v) @ st.S) / (rho * s)[:, None]
    return Channels(r, J, mc, rho, v)


def calib_G(m, st: State) -> np.ndarray:
    """(N, 3, 9) raw-domain perturbations of b (3) and of S (6 symmetric directions)."""
    N = m.shape[0]
    G = np.zeros((N, 3, 9))
    G[:, 0, 0] = G[:, 1, 1] = G[:, 2, 2] = -1.0
    Sinv = np.linalg.inv(st.S)
    x = m - st.b
    for i, (k, l) in enumerate(_SYM):
        E = np.zeros((3, 3))
        E[k, l] = E[l, k] = 1.0
        G[:, :, 3 + i] = x @ (Sinv @ E).T
    return G


@dataclass
class Term:
    """One mean effect inside a model: its form, the chosen nonlinear settings and G(frame, m, state)."""

    name: str
    design: dict
    G: object               # callable (frame, m, state) -> (N, 3, k)
    k: int
    options: list | None = None     # [(design, G)] when a nonlinear setting is chosen per fit (grid)

    def with_design(self, design, G):
        return Term(self.name, design, G, self.k, self.options)


@dataclass
class ModelFit:
    state: State
    terms: list
    theta: list                 # per term (k,)
    e: np.ndarray               # (N, C) residual
    valid: np.ndarray           # (N, C)
    inlier: np.ndarray          # (N, C)
    X: np.ndarray               # (N, C, p) columns at the solution (calibration, dip0, effects)
    sigma: np.ndarray           # (C,)
    fit_mask: np.ndarray        # (N,)
    v: np.ndarray               # (N, 3)
    m_corr: np.ndarray          # (N, 3) raw minus the fitted effects
    rss: float = float("nan")
    extra: dict = field(default_factory=dict)

    @property
    def n_calib(self) -> int:
        return 9 + (1 if self.e.shape[1] == 2 else 0)

    def term_slices(self):
        out, start = [], self.n_calib
        for t in self.terms:
            out.append(slice(start, start + t.k))
            start += t.k
        return out


#: at most this many passes of the fixed point m_true = m - sum G(m_true) theta; each pass shrinks
#: the error by the effect's slope |dG/dm theta| (up to ~0.35 for a 3 uT compression at 70 uT:
#: three passes leave ~4% of the first pass's error, and more did not change the fit's residual)
OFFSET_PASSES = 3
#: the fixed point stops when a pass changes the offsets by less than this fraction of max |m|
OFFSET_TOL = 1e-7


def _effect_offsets(frame, st, terms, theta):
    """sum G(m_true) theta. A form's columns depend on the signal the effect acted on, the raw
    signal before the effect (m_true), not the recorded m = m_true + G(m_true) theta; at the
    recorded one a large effect (a 3 uT compression, whose columns change by 3 d x^2 / F^3 of
    that shift) leaves a second-order error of ~1 uT. So m_true is found by a fixed point from
    the recorded m, which converges while the effect's slope |dG/dm theta| < 1 (a small effect
    in two passes; forms that do not read m in one more). The forms are read at the recorded m
    averaged over 3 samples: read at the noisy m, the inversion would pass the noise through
    the form's slope once more (1 / (1 - 3 d x^2 / F^3), up to 1.5 for that compression, a
    residual wider than the replicas'); the average's own error, a third of the signal's second
    difference times that slope, is ~0.02 uT there."""
    d = np.zeros_like(frame.m)
    m_read = getattr(frame, "m_smooth", frame.m)
    tol = OFFSET_TOL * max(float(np.max(np.abs(frame.m))), 1e-300)
    for _ in range(OFFSET_PASSES):
        at = m_read - d
        new = np.zeros_like(frame.m)
        for term, th in zip(terms, theta):
            new += np.einsum("nkp,p->nk", term.G(frame, at, st), th)
        done = float(np.max(np.abs(new - d))) <= tol if new.size else True
        d = new
        if done:
            break
    return d


def noise_free_point(m, st: State) -> np.ndarray:
    """(N, 3) where the fit and the tests read their columns, free of the sample's own noise:
    the direction of its two neighbours' average, m_hat = (m[n-1] + m[n+1]) / 2 (one neighbour
    at the ends), put on the fitted sphere, b + S^-1 F u with u = S (m_hat - b) / |S (m_hat - b)|.
    Where the two neighbours lie more than NEIGHBOUR_SPREAD_RAD apart (calibrated directions)
    and further apart than noise makes them, their average no longer stands for the sample, and
    the sample's own direction is used (m_hat = m[n], put on the sphere the same way).

    Why: the norm residual of a sample is mostly its own noise along the field, e ~ v . n. A
    column read at the noisy sample carries that noise too (x^3 at x + n has 3 x^2 n; the
    ellipsoid's columns are linear in x), so residual and column share it and their product has
    a mean no replica (whose noise is its own) has. The cubic columns are ~95% collinear with the
    ellipsoid's, so that shared noise survives their orthogonalisation: on 10^4 samples at 0.6 uT
    of noise, or 2 x 10^4 at 0.1 uT, a cubic term "fired" at 3-5 sigma on nulls. The neighbours
    share no white noise with the sample, and the sphere drops what is left along the field
    (coloured noise; the neighbours' mean curvature, ~ -dt^2 w^2 m / 2, is radial).

    Why the spread limit: when the motion between samples is large (a 50 Hz recording decimated
    by 50, 0.8 rad between samples), the neighbours' average points elsewhere and the columns
    read there are weak instruments: on 10^6-sample hand nulls 3 of 7 alarmed, in every bin, on
    the direction-anisotropy regressor (the ellipsoid's shape), and no gap remained with the
    sample's own direction (seed 3700: gap index 1.21 -> 1.03, alarm 1.18). The sample's own
    direction on the sphere still drops its noise along the field; its noise across the field
    is independent of that along it for isotropic noise. The choice uses only the neighbours
    (and one robust level for the whole recording), so it does not select on the sample's own
    noise. The noise floor on the distance keeps a fit whose field is within the noise (a static
    sensor's fitted "field" of 0.3 uT, where 93% of the neighbours were "far") on the neighbours:
    without it, 5 of 60 static nulls alarmed through a doubled white-noise level.
    """
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"noise_free_point needs (N, 3) magnetometer samples, got shape {m.shape}")
    n = m.shape[0]
    if n < 3:
        return m.copy()
    mh = np.empty_like(m)
    mh[1:-1] = 0.5 * (m[:-2] + m[2:])
    mh[0], mh[-1] = m[1], m[-2]
    far = far_neighbours(m, st)
    mh[far] = m[far]
    mc = (mh - st.b) @ st.S.T
    u = mc / np.maximum(np.linalg.norm(mc, axis=1, keepdims=True), 1e-300)
    return st.b + (st.F * u) @ np.linalg.inv(st.S).T


def far_neighbours(m, st: State) -> np.ndarray:
    """(N,) bool: the samples whose two neighbours (one at the ends) no longer stand for them,
    the rule :func:`noise_free_point` uses (see its "Why the spread limit"): the neighbours'
    calibrated directions, u = S (m - b) / |S (m - b)|, lie more than NEIGHBOUR_SPREAD_RAD apart
    (half that to the one neighbour at an end) AND their distance |S (m[n+1] - m[n-1])| exceeds
    NEIGHBOUR_NOISE_K robust sds (1.4826 MAD) of the calibrated norm |S (m - b)|. All False
    below 3 samples."""
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"far_neighbours needs (N, 3) magnetometer samples, got shape {m.shape}")
    n = m.shape[0]
    far = np.zeros(n, dtype=bool)
    if n < 3:
        return far
    xc = (m - st.b) @ st.S.T
    rc = np.linalg.norm(xc, axis=1)
    uc = xc / np.maximum(rc, 1e-300)[:, None]
    # far: the neighbours' angle exceeds the limit AND their distance exceeds what the noise alone
    # makes (NEIGHBOUR_NOISE_K robust sd of the norm residual): where the fitted field is not
    # well above the noise (a sensor at rest, a fit of a few uT), the directions are noise
    # and the neighbours are kept
    lim = NEIGHBOUR_NOISE_K * 1.4826 * np.median(np.abs(rc - np.median(rc)))
    far[1:-1] = ((np.sum(uc[:-2] * uc[2:], axis=1) < np.cos(NEIGHBOUR_SPREAD_RAD))
                 & (np.linalg.norm(xc[2:] - xc[:-2], axis=1) > lim))
    for i, j in ((0, 1), (n - 1, n - 2)):                    # one neighbour at the ends
        far[i] = np.dot(uc[i], uc[j]) < np.cos(0.5 * NEIGHBOUR_SPREAD_RAD) and np.linalg.norm(xc[i] - xc[j]) > lim
    return far


def columns_at(frame, m, st: State, terms=()) -> np.ndarray:
    """(N, C, p) a model's columns (calibration, dip0, terms), all read at the points m, the
    channels' Jacobian included (e.g. at :func:`noise_free_point` for a test)."""
    return _columns(frame, m, st, channels(m, frame, st), list(terms))


def _columns(frame, m_corr, st, ch, terms):
    cols = [np.einsum("nck,nkp->ncp", ch.J, calib_G(m_corr, st))]
    C = ch.r.shape[1]
    if C == 2:
        d = np.zeros((m_corr.shape[0], 2, 1))
        d[:, 1, 0] = -1.0
        cols.append(d)
    for term in terms:
        # columns at the current linearisation point (the corrected signal), like the Jacobian
        cols.append(-np.einsum("nck,nkp->ncp", ch.J, term.G(frame, m_corr, st)))
    return np.concatenate(cols, axis=2)


def _solve(A, g):
    p = A.shape[0]
    lam = RIDGE * max(np.trace(A) / p, 1e-300)
    try:
        return -np.linalg.solve(A + lam * np.eye(p), g)
    except np.linalg.LinAlgError:
        return -np.linalg.lstsq(A + lam * np.eye(p), g, rcond=None)[0]


def _normal(X, e, w, sigma):
    """sum over samples and channels of w x x^T / s^2 and w x e / s^2."""
    Xs = X / sigma[None, :, None]
    es = e / sigma[None, :]
    Xw = Xs * w[:, :, None]
    A = np.einsum("ncp,ncq->pq", Xw, Xs)
    g = np.einsum("ncp,nc->p", Xw, es)
    return A, g


def fit_model(frame, start: State, terms, valid, sigma, fit_mask=None, iters=4, inlier=None) -> ModelFit:
    """Gauss-Newton fit of calibration + dip0 + the terms' parameters on ``fit_mask`` samples."""
    fit_mask = np.ones(frame.n, dtype=bool) if fit_mask is None else fit_mask
    st = start.copy()
    theta = [np.zeros(t.k) for t in terms]
    inl = valid.copy() if inlier is None else (inlier & valid)
    for it in range(iters + 1):
        m_corr = frame.m - _effect_offsets(frame, st, terms, theta)
        ch = channels(m_corr, frame, st)
        e = ch.r
        if it > 0 or inlier is None:
            inl = valid & (np.abs(e) < INLIER_K * sigma[None, :])
        # columns at the noise-free point (instruments): at convergence X' W e = 0 holds with
        # columns that share no noise with e, so no term is fitted to the noise itself
        X = columns_at(frame, noise_free_point(m_corr, st), st, terms)
        if it == iters:
            break
        w = (inl & fit_mask[:, None]).astype(np.float64)
        A, g = _normal(X, e, w, sigma)
        d = _solve(A, g)
        st.b = st.b + d[:3]
        dS = np.zeros((3, 3))
        for i, (k, l) in enumerate(_SYM):
            dS[k, l] += d[3 + i]
            if k != l:
                dS[l, k] += d[3 + i]
        st.S = st.S + dS
        pos = 9
        if e.shape[1] == 2:
            st.dip0 += d[9]
            pos = 10
        for j, t in enumerate(terms):
            theta[j] = theta[j] + d[pos:pos + t.k]
            pos += t.k
    w = inl & fit_mask[:, None]
    rss = float(np.sum((e / sigma[None, :]) ** 2 * w))
    return ModelFit(state=st, terms=list(terms), theta=theta, e=e, valid=valid, inlier=inl, X=X, sigma=sigma,
                    fit_mask=fit_mask, v=ch.v, m_corr=m_corr, rss=rss)


def quick_rss(frame, base: ModelFit, term: Term) -> float:
    """Training RSS after one linear step from a fitted model with one more term (grid searches);
    the term's column is read at the noise-free point, like the fit's."""
    Xe = columns_at(frame, noise_free_point(base.m_corr, base.state), base.state, [term])[:, :, -term.k:]
    X = np.concatenate([base.X, Xe], axis=2)
    w = (base.inlier & base.fit_mask[:, None]).astype(np.float64)
    A, g = _normal(X, base.e, w, base.sigma)
    d = _solve(A, g)
    e = base.e + np.einsum("ncp,p->nc", X, d)
    return float(np.sum((e / base.sigma[None, :]) ** 2 * w))


def block_normals(fit: ModelFit, block, n_blocks):
    """Per-block normal equations (A_b, g_b) on the fit's own samples (for block bootstraps)."""
    w = (fit.inlier & fit.fit_mask[:, None]).astype(np.float64)
    Xs = fit.X / fit.sigma[None, :, None]
    es = fit.e / fit.sigma[None, :]
    p = Xs.shape[2]
    A = np.zeros((n_blocks, p, p))
    g = np.zeros((n_blocks, p))
    for b in range(n_blocks):
        sl = block == b
        if sl.any():
            Xw = Xs[sl] * w[sl][:, :, None]
            A[b] = np.einsum("ncp,ncq->pq", Xw, Xs[sl])
            g[b] = np.einsum("ncp,nc->p", Xw, es[sl])
    return A, g


def bootstrap_theta(fit: ModelFit, A_b, g_b, mult):
    """Parameters after refitting with block multiplicities ``mult`` (one linear step)."""
    A = np.tensordot(mult, A_b, axes=1)
    g = np.tensordot(mult, g_b, axes=1)
    d = _solve(A, g)
    out, pos = [], fit.n_calib
    for t, th in zip(fit.terms, fit.theta):
        out.append(th + d[pos:pos + t.k])
        pos += t.k
    return out


def project(r, valid, X, fit_mask, sigma, valid_common):
    """Refit replicas of the residual channels (R, N, C) with the columns X of a model.

    Each replica is generated at the model's own parameters, so one weighted least-squares step
    is its fit. The normal matrix is shared: that of all common-valid fit samples, minus each
    replica's own outliers and masked samples (a few percent), so R replicas cost about one fit.
    """
    R = r.shape[0]
    inl = valid & (np.abs(r) < INLIER_K * sigma[None, None, :])
    w = inl & fit_mask[None, :, None]
    base = valid_common & fit_mask[:, None]
    Xs = X / sigma[None, :, None]
    A0, _ = _normal(X, np.zeros(X.shape[:2]), base.astype(np.float64), sigma)
    rs = r / sigma[None, None, :]
    g = np.einsum("rnc,ncp->rp", rs * w, Xs)
    e = np.empty_like(r)
    for i in range(R):
        drop = base & ~w[i]
        A = A0.copy()
        if drop.any():
            n_idx, c_idx = np.nonzero(drop)
            Xd = Xs[n_idx, c_idx]
            A -= Xd.T @ Xd
        extra = w[i] & ~base
        if extra.any():
            n_idx, c_idx = np.nonzero(extra)
            Xd = Xs[n_idx, c_idx]
            A += Xd.T @ Xd
        d = _solve(A, g[i])
        e[i] = r[i] + np.einsum("ncp,p->nc", X, d)
    return e


def with_state(fit: ModelFit, **kw) -> ModelFit:
    return replace(fit, **kw)
