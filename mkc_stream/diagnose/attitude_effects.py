"""The effect tests of the attitude-aided diagnosis: does the vector residual follow a logged aux signal?

Residual (attitude.py): r_kc = m_kc - (A h_k + b)_c - dpsi(t_k) g_kc, channels c = x, y, z, the baseline
knowing no power or temperature term. Each effect is a function of a logged column u_k (p columns: the
current delayed by tau; the throttle and its square; the temperature through a first-order lag), with a
coefficient K_i (p,) per sensor axis i, tested as
    r_kc = a_c + sum_i u_perp,k[c, i]^T K_i + e_kc,
fitted on the training blocks and scored on the held-out ones (frame.py's interleaved blocks).

Why u_perp and not u: the baseline, fitted without the effect, has already taken into A, b and the
yaw-error term dpsi g the part of the effect those regressors can mimic (a current that rises while
the vehicle heads north looks partly like soft iron; one that follows a slow turn like a yaw error). By
the Frisch-Waugh-Lovell theorem the coefficient of a column in the joint model equals that of its
residual after projecting out the baseline's regressors, u_perp = u - Z (Z^T C Z + P)^-1 Z^T C u, Z the
baseline's stacked columns (h_k, 1 per channel and phi_j(t) g_kc, whose coefficients the three channels
share), C its kernel weights w_kc / d_c^2, P the yaw prior. Because the yaw term is shared, the column of
axis i leaves a mark on the other channels: u_perp,k[c, i] is that mark in channel c, and the three
channels are fitted together. The baseline's held constraints are not imposed (a larger nuisance space:
if anything, conservative). Measured on simulated flights of flight/simulated.py (seeds 0-3, 300 s,
K = (0.10, -0.05, 0.15) uT/A, 3 deg of yaw error): regressing on u itself gave K_x 0.024-0.070, on u_perp
0.080-0.098.

Fit: Huber's M-estimator (k = 1.345, each channel in units of its robust sd 1.4826 MAD, iteratively
reweighted) so the disturbance bursts do not lead. Its 95% intervals: a cluster-robust (sandwich)
covariance with the training blocks as clusters, theta's influence s (Z^T Psi' Z)^-1 z_k psi(u_k) summed
over the rows and channels of each block, times G/(G-1), and t with G - 1 degrees of freedom.

Significance: a circular time-shift test. The statistic is the cluster-robust Wald statistic W of the
effect's 3p coefficients (a weighted least squares with the Huber weights of r alone, fixed, so every
shift is scored alike); its null distribution is W with the column shifted in time against the residual
by SHIFTS offsets from 10% to 90% of the recording (wrapping round), p = (1 + #{W_shift >= W}) /
(1 + SHIFTS). Why: a flight's residual and its aux signals are both correlated over seconds to minutes
(gusts, the attitude's errors, a baseline misfit over one stretch; throttle steps, a warm-up), and a shift
keeps both autocorrelations exactly while breaking only their alignment, without choosing a lag or a
bandwidth. The parametric alternative (W read against F(3p, G - 3p), G = 16 clusters; reported as
p_value_wald_f) was too liberal: on 30 null flights of tools/study_attitude_diagnosis.py it found the
throttle 3 times and the current once at the 1% level, one of them a stretch where the baseline's yaw
term ran off (52 deg) and the current, stepping at the same time, "explained" 92% of the held-out residual.
The delay and the lag are chosen on the training blocks (least Huber objective, every candidate at the scale
of the fit without the effect) and tested at that choice;
the held-out check guards against it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Huber's tuning constant, in robust standard deviations (95% efficiency for Gaussian errors)
HUBER_K = 1.345
#: delays (s) of the current tried: the magnetometer sees the current this late, or (negative) the
#: logged current is the late one (a filtered or late-logged sensor); vector_fit's range, a coarser step
CURRENT_DELAYS = tuple(np.round(np.arange(-0.5, 0.5001, 0.02), 3))
#: first-order thermal lags (s) of the die behind the temperature column (thermal.py's grid)
THERMAL_LAGS = (0.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0)
#: time shifts of the circular shift test (module doc): the smallest p it can give is 1 / (SHIFTS + 1)
SHIFTS = 199
#: the aux column each effect is a function of
COLUMN = {"current_hard_iron": "current", "throttle_hard_iron": "throttle", "temperature_offset": "temp"}
#: the least span of a column for its effect to be testable (the library's testable rules)
MIN_SPAN = {"current": (0.5, "A"), "throttle": (0.1, ""), "temp": (2.0, "degC")}


class BaselineProjector:
    """u -> u_perp (module doc) for the baseline's regressors X (N, 4), its weights C (N, 3), the yaw
    basis (flight.yaw_error.YawBasis or None) and its regressor g (N, 3)."""

    def __init__(self, X, C, basis=None, g=None):
        self.X, self.C, self.basis, self.g = X, C, basis, g
        nx = X.shape[1]
        nb = 0 if basis is None else basis.n
        N = np.zeros((3 * nx + nb, 3 * nx + nb))
        for i in range(3):
            N[i * nx:(i + 1) * nx, i * nx:(i + 1) * nx] = (X * C[:, i:i + 1]).T @ X
            if basis is not None:
                N[i * nx:(i + 1) * nx, 3 * nx:] = basis.cross(X, C[:, i] * g[:, i])
        if basis is not None:
            N[3 * nx:, :3 * nx] = N[:3 * nx, 3 * nx:].T
            pen = basis.prior_precision * (np.eye(nb) + basis.MEAN_WEIGHT * np.ones((nb, nb)))
            N[3 * nx:, 3 * nx:] = basis.gram(np.sum(C * g * g, axis=1)) + pen
        dg = np.sqrt(np.maximum(np.diag(N), 1e-300))
        self._dg = dg
        self._Ninv = np.linalg.pinv(N / np.outer(dg, dg))
        self.nx, self.nb = nx, nb

    def perp(self, u) -> np.ndarray:
        """(N, 3, 3, p): [k, c, i, j] = channel c of column j placed in channel i, after the baseline's
        regressors are projected out (the yaw term's coefficients are shared by the channels, so a column
        of one channel leaves its mark on the others)."""
        u = np.asarray(u, dtype=np.float64).reshape(self.X.shape[0], -1)
        n, p = u.shape
        nx = self.nx
        out = np.zeros((n, 3, 3, p))
        for i in range(3):
            rhs = np.zeros((3 * nx + self.nb, p))
            cu = u * self.C[:, i:i + 1]
            rhs[i * nx:(i + 1) * nx] = self.X.T @ cu
            if self.basis is not None:
                rhs[3 * nx:] = np.stack([self.basis.project(cu[:, j] * self.g[:, i]) for j in range(p)], 1)
            z = (self._Ninv @ (rhs / self._dg[:, None])) / self._dg[:, None]
            dpsi = (np.stack([self.basis.eval(z[3 * nx:, j]) for j in range(p)], 1)
                    if self.basis is not None else None)
            for c in range(3):
                fit = self.X @ z[c * nx:(c + 1) * nx]
                if dpsi is not None:
                    fit = fit + dpsi * self.g[:, c:c + 1]
                out[:, c, i, :] = (u if c == i else 0.0) - fit
        return out


def _wls(Z, y, w):
    """argmin sum w (y - Z theta)^2 by the normal equations (few columns), column-equilibrated."""
    Zw = Z * w[:, None]
    N = Zw.T @ Z
    dg = np.sqrt(np.maximum(np.diag(N), 1e-300))
    return (np.linalg.pinv(N / np.outer(dg, dg)) @ (Zw.T @ y / dg)) / dg


def huber_fit(y, Z, k=HUBER_K, iters=30):
    """Huber M-estimate of y ~ Z theta: (theta, scale, psi(u), psi'(u)), u = (y - Z theta) / scale; the scale
    1.4826 MAD of the residuals, re-estimated at each reweighting."""
    theta = _wls(Z, y, np.ones_like(y))
    s = 1.0
    for _ in range(iters):
        e = y - Z @ theta
        s = max(1.4826 * float(np.median(np.abs(e - np.median(e)))), 1e-12)
        new = _wls(Z, y, np.minimum(1.0, k / np.maximum(np.abs(e / s), 1e-300)))
        done = np.max(np.abs(new - theta)) <= 1e-9 * (1.0 + np.max(np.abs(theta)))
        theta = new
        if done:
            break
    u = (y - Z @ theta) / s
    return theta, s, np.clip(u, -k, k), (np.abs(u) < k).astype(np.float64)


def huber_objective(y, Z, theta, s, k=HUBER_K) -> float:
    u = np.abs((y - Z @ theta) / s)
    return float(np.sum(np.where(u < k, 0.5 * u * u, k * u - 0.5 * k * k)))


@dataclass
class Candidate:
    """One column set of an effect: its label (delay or lag) and the raw columns u (N, p)."""
    label: dict
    u: np.ndarray


def candidates(name, aux, t, duration):
    """The column sets tried for an effect (module doc), or (None, reason) when the recording cannot test it."""
    from ..sim.effects.base import first_order_lag
    from ..flight.delay import delayed

    col = COLUMN[name]
    if col not in aux:
        return None, f"the recording has no {col!r} column"
    x = aux[col]
    fin = np.isfinite(x)
    if fin.sum() < 0.5 * x.size:
        return None, f"{(~fin).mean():.0%} of the {col!r} values are missing"
    span = float(np.ptp(x[fin]))
    need, unit = MIN_SPAN[col]
    if span < need:
        return None, f"{col!r} varies by only {span:.3g} {unit} (needs >= {need:g} {unit})".replace("  ", " ")
    good = np.flatnonzero(fin)
    xf = np.interp(t, t[good], x[good])          # holes bridged linearly; counted in the result (aux_rows_bridged)
    if name == "current_hard_iron":
        return [Candidate({"delay_s": float(d)}, delayed(t, xf[:, None], float(d))) for d in CURRENT_DELAYS], None
    if name == "throttle_hard_iron":
        return [Candidate({}, np.stack([xf, xf * xf], axis=1))], None
    return [Candidate({"lag_s": float(tau)}, first_order_lag(t, xf, tau)[:, None])
            for tau in THERMAL_LAGS if tau <= duration], None


@dataclass
class StackedFit:
    theta: np.ndarray        # (3 + q,): the channels' intercepts, then the effect's coefficients
    infl: np.ndarray         # (N_train, 3 + q): influence of each training sample (its three channels) on theta
    s: float                 # the fit's Huber scale, in units of the channels' robust sds


def robust_scales(r) -> np.ndarray:
    """1.4826 MAD of each channel of r (N, 3), the unit each channel is measured in by the stacked fit."""
    return np.maximum(1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0), 1e-12)


def design(Up) -> np.ndarray:
    """(N, 3, 3 + q): per row and channel, the channel's intercept and the projected columns Up (N, 3, 3, p)
    flattened over (source channel, column): coefficient 3 + i p + j is K[i, j]."""
    n = Up.shape[0]
    Z = np.zeros((n, 3, 3 + 3 * Up.shape[3]))
    Z[:, np.arange(3), np.arange(3)] = 1.0
    Z[:, :, 3:] = Up.reshape(n, 3, -1)
    return Z


def stacked_fit(r, Z, scale) -> StackedFit:
    """Huber fit of the three channels of r (n, 3) at once on Z (n, 3, q), each channel divided by its scale."""
    n = r.shape[0]
    Zs = (Z / scale[None, :, None]).reshape(3 * n, -1)
    ys = (r / scale[None, :]).reshape(-1)
    theta, s, psi, dpsi = huber_fit(ys, Zs)
    B = (Zs * dpsi[:, None]).T @ Zs
    infl = (s * (Zs * psi[:, None]) @ np.linalg.pinv(B).T).reshape(n, 3, -1).sum(axis=1)
    return StackedFit(theta, infl, s)


def objective_at(r, Z, scale, theta, s) -> float:
    """The Huber objective of theta on the stacked channels (as stacked_fit divides them) at the given scale
    s: models compare on it only at a common s (a worse fit has a larger scale of its own, which would
    shrink its objective)."""
    n = r.shape[0]
    return huber_objective((r / scale[None, :]).reshape(-1), (Z / scale[None, :, None]).reshape(3 * n, -1), theta, s)


def held_out_ss(r, train, Z, scale) -> float:
    """Sum of squares (r's unit^2) on the held-out rows of the model Z fitted on the training rows."""
    f = stacked_fit(r[train], Z[train], scale)
    test = ~train
    return float(np.sum((r[test] - Z[test] @ f.theta) ** 2))


@dataclass
class EffectTest:
    name: str
    testable: bool
    reason: str | None = None
    found: bool = False
    p_value: float = math.nan
    level: float = math.nan
    size: dict = field(default_factory=dict)
    held_out: dict = field(default_factory=dict)
    label: dict = field(default_factory=dict)
    prediction: np.ndarray | None = field(default=None, repr=False)   # (N, 3) the effect's part of r (all rows)
    columns: np.ndarray | None = field(default=None, repr=False)      # (N, 3, 3 p) its columns in the design
    p_value_wald_f: float = math.nan     # the parametric reading of the same statistic (module doc), for comparison

    def to_json(self) -> dict:
        return {"name": self.name, "testable": self.testable, "reason": self.reason, "found": self.found,
                "p_value": None if not math.isfinite(self.p_value) else float(self.p_value),
                "level": None if not math.isfinite(self.level) else float(self.level),
                "p_value_wald_f": None if not math.isfinite(self.p_value_wald_f) else float(self.p_value_wald_f),
                "size": self.size, "held_out": self.held_out, **self.label}


def _delay_label(label, e, se, G):
    """The chosen delay with its 95% interval (t, G - 1 degrees of freedom), or None with the reason: at an
    end of the search, or an interval wider than flight.delay.DELAY_DETERMINED (s) each side."""
    from scipy.stats import t as student

    from ..flight.delay import DELAY_DETERMINED

    q = float(student.ppf(0.975, G - 1))
    lo, hi = CURRENT_DELAYS[0], CURRENT_DELAYS[-1]
    tau = label["delay_s"]
    if tau in (lo, hi):
        label.update(delay_s=None, delay_note=f"at the end of the search ({lo * 1e3:g} to {hi * 1e3:g} ms): "
                                              "not determined by this recording")
    elif not (math.isfinite(e) and q * se <= DELAY_DETERMINED):
        label.update(delay_s=None, delay_note=f"not determined by this recording (95% interval +-{q * se * 1e3:.0f} "
                                              f"ms about {tau * 1e3:.0f} ms: the current moves too slowly)")
    else:
        label.update(delay_s=tau + e, delay_ci95_s=[tau + e - q * se, tau + e + q * se])


def _size(name, K, V, G, unit):
    """Per-axis size and 95% interval (t with G-1 degrees of freedom) in the library's units."""
    from scipy.stats import t as student

    q = float(student.ppf(0.975, G - 1))
    p = K.shape[1]
    if name == "throttle_hard_iron":      # offset at full throttle against zero: p + q (electrical.py)
        L = np.zeros((3, 3 * p))
        for i in range(3):
            L[i, i * p:(i + 1) * p] = 1.0
        val = L @ K.reshape(-1)
        sd = np.sqrt(np.maximum(np.diag(L @ V @ L.T), 0.0))
    else:
        val = K[:, 0]
        sd = np.sqrt(np.maximum(np.diag(V), 0.0))
    if name == "temperature_offset":
        f, u = (1e3, "nT/degC") if unit == "uT" else (1.0, f"{unit}/degC")
    else:
        f, u = 1.0, f"{unit}/A" if name == "current_hard_iron" else unit
    out = {"value": [float(v * f) for v in val], "ci95": [[float((v - q * s) * f), float((v + q * s) * f)]
                                                         for v, s in zip(val, sd)],
           "unit": u, "norm": float(np.linalg.norm(val) * f)}
    if name == "throttle_hard_iron":
        out["meaning"] = "offset at full throttle against zero throttle"
    return out


def _cluster_cov(fit, idx, G, first) -> np.ndarray:
    """Cluster-robust covariance (module doc) of the coefficients first.. of a stacked fit, idx (n_train,)
    the training block of each row."""
    S = np.stack([np.bincount(idx, fit.infl[:, j], G) for j in range(first, fit.infl.shape[1])], 1)
    return S.T @ S * G / max(G - 1, 1)


def delay_interval(t, u, r, train, idx, G, proj, scale):
    """(correction, standard error) in s of the current's delay at the chosen grid point, by linearising
    the delayed column about it: K_i c(t - tau - e) ~ K_i u - e K_i du/dt, so the model with the columns
    u and du/dt per axis has the coefficients K_i and g_i = -e K_i; e = -(K . g) / (K . K), its
    variance by the delta method from the cluster-robust covariance of (K, g). A smooth current (a
    flat profile in the delay) gives a wide interval: the grid's choice is then not a measurement."""
    with np.errstate(divide="ignore", invalid="ignore"):       # repeated timestamps: no rate there
        du = np.gradient(u[:, 0], t)[:, None] if t.shape[0] > 2 else np.zeros_like(u)
    du = np.nan_to_num(du, nan=0.0, posinf=0.0, neginf=0.0)
    fit = stacked_fit(r[train], design(proj.perp(np.concatenate([u, du], axis=1)))[train], scale)
    V = _cluster_cov(fit, idx, G, 3)
    c = fit.theta[3:].reshape(3, 2)                 # [K_i, g_i] per sensor axis i
    K, g = c[:, 0], c[:, 1]
    kk = float(K @ K)
    if not kk > 0:
        return math.nan, math.inf
    e = -float(K @ g) / kk
    grad = np.zeros((3, 2))
    grad[:, 0] = -g / kk + 2.0 * float(K @ g) * K / kk ** 2
    grad[:, 1] = -K / kk
    grad = grad.reshape(-1)
    return e, math.sqrt(max(float(grad @ V @ grad), 0.0))


def _cluster_wald(r, Z, w, idx, G, first) -> float:
    """Cluster-robust Wald statistic of the coefficients first.. of the weighted least squares of the stacked
    channels r (n, 3) on Z (n, 3, q) with fixed weights w (n, 3); idx (n,) the cluster of each row."""
    n, q = r.shape[0], Z.shape[2]
    Zs, ys, ws = Z.reshape(3 * n, q), r.reshape(-1), w.reshape(-1)
    theta = _wls(Zs, ys, ws)
    B = (Zs * ws[:, None]).T @ Zs
    infl = ((Zs * (ws * (ys - Zs @ theta))[:, None]) @ np.linalg.pinv(B).T).reshape(n, 3, q).sum(axis=1)
    S = np.stack([np.bincount(idx, infl[:, j], G) for j in range(first, q)], 1)
    k = theta[first:]
    try:
        return float(k @ np.linalg.solve(S.T @ S, k))
    except np.linalg.LinAlgError:
        return 0.0


def shift_p_value(r, train, idx, G, proj, u, scale, shifts=SHIFTS) -> tuple[float, float]:
    """(p, W) of the circular time-shift test (module doc): the cluster-robust Wald statistic W of the column u
    against the same statistic with u shifted in time by `shifts` evenly spaced offsets between 10% and 90% of
    the recording, which keeps the autocorrelation of both series and breaks only their alignment."""
    rt = r[train] / scale[None, :]
    u0 = (rt - np.median(rt, axis=0)) / 1.4826 / np.maximum(np.median(np.abs(rt - np.median(rt, axis=0)), axis=0), 1e-300)
    w = np.minimum(1.0, HUBER_K / np.maximum(np.abs(u0), 1e-300))      # Huber weights of r alone: fixed
    n = r.shape[0]

    def stat(col):
        return _cluster_wald(rt, design(proj.perp(col))[train] / scale[None, :, None], w, idx, G, 3)

    W = stat(u)
    offs = np.unique(np.round(n * np.linspace(0.1, 0.9, shifts)).astype(np.int64))
    null = np.array([stat(np.roll(u, int(o), axis=0)) for o in offs])
    return float((1 + np.sum(null >= W)) / (1 + null.size)), W


def run_effect_test(name, aux, t, duration, r, train, block, proj, unit, level) -> EffectTest:
    """Fit, test and score one effect on the residual r (N, 3) (module doc)."""
    from scipy.stats import f as fisher

    cands, why = candidates(name, aux, t, duration)
    if cands is None:
        return EffectTest(name, False, why)
    col = COLUMN[name]
    bridged = int((~np.isfinite(aux[col])).sum())
    test = ~train
    scale = robust_scales(r[train])
    s0 = stacked_fit(r[train], design(np.zeros((r.shape[0], 3, 3, 0)))[train], scale).s   # the common scale
    best = None
    for c in cands:
        Up = proj.perp(c.u)
        Z = design(Up)
        f = stacked_fit(r[train], Z[train], scale)
        obj = objective_at(r[train], Z[train], scale, f.theta, s0)
        if best is None or obj < best[0]:
            best = (obj, c, Up, Z, f)
    _, cand, Up, Z, fit = best
    p = cand.u.shape[1]
    # cluster-robust covariance of the effect's coefficients over the three channels (module doc)
    blocks = np.unique(block[train])
    G = blocks.size
    idx = np.searchsorted(blocks, block[train])
    V = _cluster_cov(fit, idx, G, 3)
    K = fit.theta[3:].reshape(3, p)
    k = K.reshape(-1)
    try:
        W = float(k @ np.linalg.solve(V, k))
    except np.linalg.LinAlgError:
        W = 0.0
    dof = G - 3 * p
    p_wald = float(fisher.sf(W * dof / (3 * p * (G - 1)), 3 * p, dof)) if dof > 0 else math.nan
    pval, _ = shift_p_value(r, train, idx, G, proj, cand.u, scale)
    # held-out: the intercepts alone against intercepts + effect, both fitted on the training blocks
    a0 = stacked_fit(r[train], Z[train, :, :3], scale).theta
    pred = Z[:, :, 3:] @ fit.theta[3:]
    before = r[test] - a0[None, :]
    after = r[test] - fit.theta[None, :3] - pred[test]
    ss0, ss1 = float(np.sum(before ** 2)), float(np.sum(after ** 2))
    share = 1.0 - ss1 / ss0 if ss0 > 0 else math.nan
    held = {"aux_rows_bridged": bridged, "rms_before": np.sqrt(np.mean(before ** 2, axis=0)).tolist(),
            "rms_after": np.sqrt(np.mean(after ** 2, axis=0)).tolist(), "unit": unit,
            "variance_explained": share, "samples": int(test.sum())}
    found = bool(math.isfinite(pval) and pval < level and share > 0)
    label = dict(cand.label)
    if "delay_s" in label and found:
        _delay_label(label, *delay_interval(t, cand.u, r, train, idx, G, proj, scale), G)
    elif "delay_s" in label and not found:
        label["delay_s"] = None              # no effect: no delay to speak of
    size = _size(name, K, V, G, unit)
    size["clusters"] = int(G)
    return EffectTest(name, True, None, found, pval, level, size, held, label, pred, Z[:, :, 3:], p_wald)
