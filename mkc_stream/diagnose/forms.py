"""How the diagnoser fits each effect of the library: its fitting form.

Mean effects (a deterministic change of the raw signal) are linear in their parameters once
the nonlinear settings are fixed: dm = G(t) theta. G comes from the forward model's
derivative with respect to its parameters (e.g. temperature_offset: I_3 (T_lag(t) - mean);
temperature_scale: diag(m - b) (T_lag - mean); hard_iron_step: I_3 [t >= t0]); settings that
are not linear (thermal lag tau, step time t0, hysteresis rate) are found by a grid search on
training blocks. Each design returns its G as a function of (frame, m, state) so that the
Gauss-Newton fit can re-evaluate it at the current hard iron.

Stochastic and clock effects are estimated from the data (autocovariance excess over the
replicas for coloured noise, block-to-block hard-iron wander for a random walk, the lattice of
raw values, pile-ups at the extremes, the statistics of time steps) and then *added to the
replicas*, which is how a simulator would carry them.

cross_axis is observed only through its antisymmetric part, a rotation against the
accelerometer: its form is the misalignment's, and the two are always reported as ambiguous.

Size: one fitting form per effect of the library, registered together in FORMS, sharing the
design helpers (Env, the tau grids, block offsets, the noise statistics); a split into mean and
estimated forms is possible but not done yet (the two halves share those helpers).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import nnls

from ..sim.effects import EFFECTS
from ..sim.effects.base import first_order_lag
from ..sim.trajectory import moving_average
from .baseline import robust_sd
from .panel import time_regressors

UNIT_TO_UT = {"uT": 1.0, "nT": 1e-3, "mT": 1e3, "T": 1e6, "G": 100.0, "gauss": 100.0, "Gauss": 100.0, "mG": 0.1}
F_REF_UT = 50.0


@dataclass
class Env:
    frame: object
    base: object
    cache: dict = field(default_factory=dict)

    @property
    def to_uT(self):
        return UNIT_TO_UT.get(self.frame.unit)

    @property
    def F_ref(self) -> float:
        """50 uT in the recording's unit, or the fitted field when the unit is unknown."""
        f = self.to_uT
        return F_REF_UT / f if f else float(self.base.fit.state.F)

    def lagged(self, name, tau):
        key = ("lag", name, tau)
        if key not in self.cache:
            x = first_order_lag(self.frame.t, self.frame.aux[name], tau)
            self.cache[key] = x - x.mean()
        return self.cache[key]

    def mdot(self):
        if "mdot" not in self.cache:
            ms = moving_average(self.frame.m, 3)
            self.cache["mdot"] = np.gradient(ms, self.frame.t, axis=0)
        return self.cache["mdot"]

    def field_unit(self, x, nano=False):
        """(value, unit label) of a field-like quantity in the recording's unit."""
        f = self.to_uT
        if f is None:
            return float(x), self.frame.unit
        return float(x) * f * (1e3 if nano else 1.0), ("nT" if nano else "uT")


def _diag(x):
    """(N, 3, 3) with x (N,) or (N, 3) on the diagonal."""
    x = np.asarray(x)
    out = np.zeros((x.shape[0], 3, 3))
    for j in range(3):
        out[:, j, j] = x if x.ndim == 1 else x[:, j]
    return out


@dataclass
class MeanForm:
    name: str
    designs: Callable          # (env) -> list of design dicts
    G: Callable                # (env, design) -> callable(frame, m, state) -> (N, 3, k)
    k: int
    magnitude: Callable        # (env, design, theta) -> {"value": v, "unit": u, ...}
    kind: str = "mean"
    alias_of: str | None = None


@dataclass
class EstimatedForm:
    name: str
    kind: str                  # "noise", "clock" or "mask"
    estimate: Callable         # (env, ctx, mult) -> params dict or None
    replica: Callable          # (env, params) -> list of (effect object, params) for the simulator
    magnitude: Callable        # (env, params) -> dict
    mask: Callable | None = None   # (env, params, raw (N, 3)) -> (N,) usable samples
    alias_of: str | None = None
    # (env, ctx, mult, spread) -> params: a second estimate, weighted by the spread of the replicas
    # of ``spread`` (an evaluation carrying a previous estimate; None on the first pass), for an
    # effect whose own realisation dominates the first estimate's errors (Engine.extend)
    refine: Callable | None = None


# ---------------------------------------------------------------------------------------------
# physical-range priors
# ---------------------------------------------------------------------------------------------

#: A fitted deterministic effect whose size exceeds PRIOR_FACTOR times the top of the library's
#: realistic range (for a vector: its per-component top times sqrt(components)) is not a
#: physical explanation: a wrong form can close a gap by absorbing it with an absurd coefficient
#: (e.g. a current-induced offset "explained" as 4000 nT/degC of thermal offset). Such a fit is
#: reported but cannot be selected or counted as an alternative explanation.
PRIOR_FACTOR = 3.0


def prior_bound(name, magnitude):
    """(bound, unit) of the plausible size of a mean effect's magnitude dict, or None when the
    library gives no range in that unit (unknown recording unit, dimensionless settings)."""
    if not magnitude or magnitude.get("value") is None:
        return None
    unit = magnitude.get("unit")
    highs = [p.high for p in EFFECTS[name].params if p.unit == unit]
    if not highs:
        return None
    k = len(magnitude["vector"]) if isinstance(magnitude.get("vector"), list) else 1
    return PRIOR_FACTOR * max(highs) * np.sqrt(k), unit


def implausible(name, magnitude):
    """A text saying why a fitted magnitude is outside the physical range, or None."""
    b = prior_bound(name, magnitude)
    if b is None or not abs(float(magnitude["value"])) > b[0]:
        return None
    return (f"the fit needs {abs(float(magnitude['value'])):.3g} {b[1]}, beyond {PRIOR_FACTOR:g}x the realistic "
            f"range (<= {b[0]:.3g} {b[1]}): not a physical explanation")


# ---------------------------------------------------------------------------------------------
# mean effects
# ---------------------------------------------------------------------------------------------

def _vec_mag(env, theta, scale, unit_nano, per):
    v = np.asarray(theta) * scale
    val, unit = env.field_unit(np.linalg.norm(v), nano=unit_nano)
    comp = [env.field_unit(x, nano=unit_nano)[0] for x in v]
    return {"value": val, "unit": unit + per, "vector": comp}


def _tau_grid(env):
    """Thermal lags tried (s): doubling steps, up to the length of the recording."""
    return [tau for tau in (0.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0) if tau <= env.frame.duration]


def _tau_pairs(env):
    """The die temperature as the temp column through two first-order thermal stages (board,
    then die; tau_a <= tau_b, 0 = no stage). The library's forward model has one stage; the
    second lets one form follow a die that sits further from the temperature sensor."""
    g = _tau_grid(env)
    return [{"tau": a, "tau2": b} for i, a in enumerate(g) for b in g[i:] if b > 0 or a == 0]


def _die(env, d):
    key = ("die", d["tau"], d["tau2"])
    if key not in env.cache:
        x = first_order_lag(env.frame.t, first_order_lag(env.frame.t, env.frame.aux["temp"], d["tau"]), d["tau2"])
        env.cache[key] = x - x.mean()
    return env.cache[key]


def _temp_offset():
    def G(env, d):
        x = _die(env, d)
        return lambda frame, m, st: _diag(x)

    def mag(env, d, th):
        out = _vec_mag(env, th, 1.0, True, "/degC")
        out.update(tau_s=[d["tau"], d["tau2"]], meaning="offset per degC of die temperature (two lag stages)")
        return out
    return MeanForm("temperature_offset", _tau_pairs, G, 3, mag)


def _temp_scale():
    def G(env, d):
        x = _die(env, d)
        return lambda frame, m, st: _diag((m - st.b) * x[:, None])

    def mag(env, d, th):
        a = np.asarray(th) * 100.0
        return {"value": float(np.linalg.norm(a)), "unit": "%/degC", "vector": a.tolist(),
                "tau_s": [d["tau"], d["tau2"]]}
    return MeanForm("temperature_scale", _tau_pairs, G, 3, mag)


def _current():
    def G(env, d):
        x = env.frame.aux["current"] - env.frame.aux["current"].mean()
        return lambda frame, m, st: _diag(x)
    return MeanForm("current_hard_iron", lambda env: [{}], G, 3, lambda env, d, th: _vec_mag(env, th, 1.0, False, "/A"))


def _throttle():
    def G(env, d):
        x = env.frame.aux["throttle"]
        a, b = x - x.mean(), x * x - (x * x).mean()
        return lambda frame, m, st: np.concatenate([_diag(a), _diag(b)], axis=2)

    def mag(env, d, th):
        out = _vec_mag(env, np.asarray(th[:3]) + np.asarray(th[3:]), 1.0, False, "")
        out["meaning"] = "offset at full throttle against zero throttle"
        return out
    return MeanForm("throttle_hard_iron", lambda env: [{}], G, 6, mag)


def _drift():
    def G(env, d):
        x = (env.frame.t - env.frame.t.mean()) / 3600.0
        return lambda frame, m, st: _diag(x)
    return MeanForm("hard_iron_drift", lambda env: [{}], G, 3, lambda env, d, th: _vec_mag(env, th, 1.0, False, "/h"))


def _step():
    def designs(env):
        t = env.frame.t
        qs = np.linspace(0.03, 0.97, 63)
        return [{"t_step": float(x)} for x in np.quantile(t, qs)]

    def G(env, d):
        x = (env.frame.t >= d["t_step"]).astype(float)
        x -= x.mean()
        return lambda frame, m, st: _diag(x)

    def mag(env, d, th):
        out = _vec_mag(env, th, 1.0, False, "")
        out["t_step_s"] = d["t_step"] - float(env.frame.t[0])
        return out
    return MeanForm("hard_iron_step", designs, G, 3, mag)


def _nonlin():
    def G(env, d):
        return lambda frame, m, st: _diag(((m - st.b) / env.F_ref) ** 3)

    def mag(env, d, th):
        out = _vec_mag(env, th, 1.0, True, "")
        out["meaning"] = "departure at 50 uT per axis" if env.to_uT else "departure at the fitted field"
        return out
    return MeanForm("scale_nonlinearity", lambda env: [{}], G, 3, mag)


def _quad_basis(v):
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([np.sqrt(15) * x * y, np.sqrt(15) * x * z, np.sqrt(15) * y * z,
                     np.sqrt(15 / 4) * (x * x - y * y), np.sqrt(5 / 4) * (x * x + y * y - 2 * z * z)], axis=1)


def norm_pattern_rms(dm_of_u) -> float:
    """RMS over directions of u . dm(u) after removing what a hard iron absorbs (degree 0 and 1):
    the observable size of a direction-dependent raw error (a quadratic raw error has null
    directions the norm cannot see, so its raw-frame size is not identifiable)."""
    from ..sim.effects.nonlinear import fibonacci_sphere

    u = fibonacci_sphere(2000)
    r = np.sum(u * dm_of_u(u), axis=1)
    A = np.column_stack([np.ones(len(u)), u])
    r = r - A @ np.linalg.lstsq(A, r, rcond=None)[0]
    return float(np.sqrt(np.mean(r * r)))


def _higher_order():
    def G(env, d):
        def g(frame, m, st):
            mc = (m - st.b) @ st.S.T
            Y = _quad_basis(mc / np.linalg.norm(mc, axis=1, keepdims=True))
            out = np.zeros((m.shape[0], 3, 15))
            for j in range(3):
                out[:, j, 5 * j:5 * j + 5] = Y
            return out
        return g

    def mag(env, d, th):
        F = float(env.base.fit.state.F)
        val, unit = env.field_unit(norm_pattern_rms(lambda u: np.stack([_quad_basis(u) @ np.asarray(th)[5 * j:5 * j + 5]
                                                                        for j in range(3)], axis=1))
                                   * (env.F_ref / F) ** 2)
        return {"value": val, "unit": unit,
                "meaning": ("RMS over directions of the field-strength error no ellipsoid can fit, at 50 uT"
                            if env.to_uT else "RMS over directions of the field-strength error no ellipsoid can fit")}
    return MeanForm("higher_order_soft_iron", lambda env: [{}], G, 15, mag)


def _hysteresis():
    def designs(env):
        return [{"k": k} for k in (0.3, 1.0, 3.0)]

    def G(env, d):
        md = env.mdot()
        eps = d["k"] * np.maximum(np.median(np.abs(md), axis=0), 1e-12)
        x = -np.tanh(md / eps)
        return lambda frame, m, st: _diag(x)

    def mag(env, d, th):
        val, unit = env.field_unit(float(np.sqrt(np.mean(np.square(th)))))
        return {"value": val, "unit": unit, "vector": [env.field_unit(x)[0] for x in th], "meaning": "loop half-width"}
    return MeanForm("hysteresis", designs, G, 3, mag)


def _rotation_G(env, d):
    def g(frame, m, st):
        mc = (m - st.b) @ st.S.T
        Sinv = np.linalg.inv(st.S)
        out = np.zeros((m.shape[0], 3, 3))
        for k in range(3):
            ek = np.zeros(3)
            ek[k] = 1.0
            out[:, :, k] = np.cross(ek, mc) @ Sinv.T
        return out
    return g


def _rotation_mag(env, d, th):
    a = np.degrees(np.asarray(th))
    return {"value": float(np.linalg.norm(a)), "unit": "deg", "vector": a.tolist(),
            "meaning": "rotation of the magnetometer against the accelerometer"}


#: the latency form's second parameter is the output filter's variance in units of (0.1 s)^2. In
#: ms^2 its column is so small beside the calibration's that the solver's relative ridge
#: (model._solve) held it far from its value (40 against 230 ms^2 after the fit's three steps)
_SPREAD_UNIT_MS = 100.0


def _latency():
    """A delay and an output filter, to second order in time: any filter with impulse-response
    mean mu and variance s^2 turns a field B(t) into B - mu B' + (s^2 + mu^2) / 2 B'' + ...
    The first-order term turns the field (tangent to the ellipsoid: the dip channel). The
    second-order term's radial part is all that changes the strength: |B_out| = |B| - s^2
    |B'|^2 / (2 |B|) (B . B' = 0 and B . B'' = -|B'|^2 for a constant strength), so a pure
    delay (s = 0) keeps it and a filter lowers it at fast turns (the norm channel, where the
    noise is the magnetometer's own and white). Its tangential part (from the angular
    acceleration) is left out: it needs the field's second derivative, noisy at 20 Hz, and the
    strength term alone explained the benchmark's filtered latencies."""
    def G(env, d):
        md = env.mdot() * 1e-3                     # per ms of delay
        # |B'|^2 in (uT/s)^2 = |tan|^2 1e6; times s^2 / 2 with s in units of _SPREAD_UNIT_MS
        scale = 0.5 * (_SPREAD_UNIT_MS * 1e-3) ** 2 * 1e6

        def g(frame, m, st):
            mc = (m - st.b) @ st.S.T
            r = np.linalg.norm(mc, axis=1, keepdims=True)
            v = mc / r
            Sinv_t = np.linalg.inv(st.S).T
            mdc = md @ st.S.T
            tan = mdc - np.sum(v * mdc, axis=1, keepdims=True) * v
            out = np.empty((m.shape[0], 3, 2))
            out[:, :, 0] = -tan @ Sinv_t
            out[:, :, 1] = (-scale * np.sum(tan * tan, axis=1, keepdims=True) / r * v) @ Sinv_t
            return out
        return g

    def mag(env, d, th):
        spread = _SPREAD_UNIT_MS * float(np.sqrt(max(th[1], 0.0)))
        return {"value": float(th[0]), "unit": "ms", "filter_spread_ms": spread,
                "meaning": "magnetometer later than the accelerometer (filter_spread_ms: RMS width "
                           "of its output filter; 0 for a pure delay)"}
    return MeanForm("latency", lambda env: [{}], G, 2, mag)


# ---------------------------------------------------------------------------------------------
# estimated (stochastic, clock, mask) effects
# ---------------------------------------------------------------------------------------------

class _Custom:
    """A replica-side forward model (per-axis generalisations of the library's forms)."""

    def __init__(self, name, stage, fn):
        self.name, self.stage, self.fn = name, stage, fn

    def apply(self, ctx, params):
        self.fn(ctx)


def _acov(z, inl, slices, K):
    """Sum of lag products and pair counts at lags 0..K over the given blocks (FFT per block)."""
    s = np.zeros(K + 1)
    c = np.zeros(K + 1)
    for sl in slices:
        x = np.where(inl[sl], z[sl], 0.0)
        msk = inl[sl].astype(float)
        if msk.sum() < 10:
            continue
        x = np.where(inl[sl], x - x.sum() / msk.sum(), 0.0)
        L = x.size
        nf = 1 << int(np.ceil(np.log2(2 * L)))
        fx = np.fft.rfft(x, nf)
        fm = np.fft.rfft(msk, nf)
        kk = min(K, L - 1)
        s[:kk + 1] += np.fft.irfft(fx * np.conj(fx), nf)[:kk + 1]
        c[:kk + 1] += np.fft.irfft(fm * np.conj(fm), nf)[:kk + 1]
    return s, np.round(c)


COLORED_GRID = 40           # correlation times tried, up to COLORED_SLOWEST blocks
COLORED_SLOWEST = 64
COLORED_FASTEST = 3         # samples: the refined grid's fastest (a faster one is the white noise's business)
COLORED_COMPONENTS = 3      # refined: a flicker-like noise spans three decades


def _colored_fit(env, ctx, mult, spread=None, refined=False):
    """Gauss-Markov components (sigma per raw axis, tau), fitted jointly to two views of the
    residual's excess over the replicas':

    * within blocks, its lag autocovariance with each block's mean removed (as the panel sees
      it): a component adds sigma^2 (pc_l e^-l/tau - D(tau)) at lag l, pc_l the norm channel's
      share of a raw-frame noise over that lag and D(tau) the variance of its block mean in the
      norm channel (:func:`_block_mean_share_norm`);
    * between blocks, the variogram of the blocks' apparent hard iron at block lags k:
      6 sigma^2 (share(u) - (1 - e^-u)^2 e^-(k-1)u / u^2), u = L / tau (block means of the process).

    The taus come from one grid (to 64 blocks; every pair, or triple, tried; amplitudes >= 0 by
    NNLS, so fewer components are fits too). One fit for both views matters: each view also holds
    the component the other one is about (a fast one sets a floor under the variogram, a slow one
    leaves part of itself inside the blocks). Each view counts once (its points weighted by
    1/sqrt(count)), each point by the replicas' sd. The effect enters only when one view shows an
    excess (3 replica sd at lag 1, or at the variogram's longest lag).

    First estimate (refined=False): two components, grid from one sample, points weighted by the
    baseline's replicas. Refined (:attr:`EstimatedForm.refine`, chosen against the first by the
    gap index in :meth:`.engine.Engine._refined`):

    * three components: a flicker-like noise spans decades (two fitted to sums of 0.5, 5 and
      30 s left a gap index of 1.6-1.7 on benchmark trials the true three closed to 1.3);
    * ``spread``, an evaluation whose replicas carry a previous estimate, gives the points' sd:
      the baseline's replicas hold white noise only (1e-4 uT^2 at a lag), while a slow noise's
      own realisation moves the long lags and the variogram by 30-50 of those sd, so the first
      fit follows one realisation's accidents (the excess is still over the baseline's replicas);
    * the baseline's white noise (third differences) already holds h(tau) of each component
      (:func:`colored_white_share`): taken off the model's lag 0, and off the replicas' white
      noise (:meth:`.engine.Engine._norm`, flagged by "white_share");
    * the grid starts at COLORED_FASTEST samples (a one-sample component stands for white noise).
    """
    frame = env.frame
    samples = _noise_samples(env, ctx)
    wide = None if spread is None else _noise_samples(env, spread)
    acv = _within_block_excess(env, samples, mult, wide)
    vgm = _variogram_excess(env, samples, mult, wide)
    if spread is None:
        fast_seen = acv is not None and acv[1][1] > 3 * acv[2][1]
        slow_seen = vgm is not None and vgm[1][-1] > 3 * vgm[2][-1]
        if not (fast_seen or slow_seen):
            return None
    L = frame.duration / frame.n_blocks
    data = []

    def views(tau):
        out = []
        if acv is not None:
            lags, _, sd, pc, sig = acv
            # the replicas' white noise already holds the component's third-difference share
            # (colored_white_share), and the replicas carry it with that much less white noise
            col = pc * np.exp(-lags / tau) - _block_mean_share_norm(env, mult, tau)
            if refined:
                col[0] -= colored_white_share(frame.dt0, tau)
            out.append(col / sig ** 2 / sd / np.sqrt(lags.size))
        if vgm is not None:
            k, _, sd = vgm
            u = L / tau
            out.append(6.0 * (block_mean_share(L, tau) - (1 - np.exp(-u)) ** 2 * np.exp(-(k - 1) * u) / (u * u))
                       / sd / np.sqrt(k.size))
        return np.concatenate(out)
    if acv is not None:
        data.append(acv[1] / acv[2] / np.sqrt(acv[0].size))
    if vgm is not None:
        data.append(vgm[1] / vgm[2] / np.sqrt(vgm[0].size))
    taus = np.geomspace((COLORED_FASTEST if refined else 1) * frame.dt0, COLORED_SLOWEST * L, COLORED_GRID)
    cols = [views(t) for t in taus]
    y = np.concatenate(data)
    best = None
    for idx in itertools.combinations(range(taus.size), COLORED_COMPONENTS if refined else 2):
        v, r = nnls(np.stack([cols[i] for i in idx], axis=1), y)
        if best is None or r < best[0]:
            best = (r, taus[list(idx)], v)
    comps = [[float(np.sqrt(a)), float(t)] for a, t in zip(best[2], best[1]) if a > 0]
    if not comps:
        return None
    return {"components": comps, "white_share": True} if refined else {"components": comps}


def _colored_refined(env, ctx, mult, spread):
    return _colored_fit(env, ctx, mult, spread, refined=True)


def colored_white_share(dt, tau):
    """Share of a Gauss-Markov noise's variance that the baseline's white-noise estimate (third
    differences, :func:`.baseline.hf_sigma`) reads as white: var(d3 x) / (20 var x) for an AR(1)
    of coefficient rho = e^-dt/tau, i.e. (20 - 30 rho + 12 rho^2 - 2 rho^3) / 20 (1 for white
    noise, about 0.6 dt / tau for a slow one). Left in, the replicas would carry that part twice,
    once as white noise and once in the component (with a fitted 0.1 s component their highest
    band stood 5.7 sd above a benchmark recording's)."""
    rho = float(np.exp(-dt / tau))
    return (20.0 - 30.0 * rho + 12.0 * rho ** 2 - 2.0 * rho ** 3) / 20.0


def _block_mean_share_norm(env, mult, tau):
    """Variance of a block's mean of the norm channel's share of a raw-frame Gauss-Markov noise
    (unit variance per axis, correlation time tau), averaged over the blocks:
    (1/L^2) sum_t sum_s (S^T v_t).(S^T v_s) e^-|t-s| dt/tau. Removing each block's mean takes
    this off the norm residual's autocovariance at every lag. It depends on how far the sensor
    turns within a block: a slow noise is nearly constant in the raw frame, but a turning sensor
    sees it from many directions, so its mean over the block is small."""
    from scipy.signal import lfilter

    key = ("bshare", round(float(tau), 9), tuple(np.flatnonzero(mult > 0)))
    if key not in env.cache:
        JS = env.base.fit.v @ env.base.fit.state.S
        rho = float(np.exp(-env.frame.dt0 / tau))
        vals = []
        for sl, w in zip(env.frame.block_slices(), mult):
            if w <= 0 or sl.stop - sl.start < 2:
                continue
            X = JS[sl]
            fwd = lfilter([1.0], [1.0, -rho], X, axis=0)
            bwd = lfilter([1.0], [1.0, -rho], X[::-1], axis=0)[::-1]
            vals.append(np.sum(X * (fwd + bwd - X)) / X.shape[0] ** 2)
        env.cache[key] = float(np.mean(vals)) if vals else 0.0
    return env.cache[key]


def _projection_acov(env, K):
    """mean over t of (S^T v_t).(S^T v_{t+k}), k = 1..K: how much of a raw-frame noise the norm
    channel keeps over a lag while the sensor turns (1 at k = 0 for S = I)."""
    key = ("pacov", K)
    if key not in env.cache:
        JS = env.base.fit.v @ env.base.fit.state.S
        n = JS.shape[0]
        env.cache[key] = np.array([np.mean(np.sum(JS[:n - k] * JS[k:], axis=1)) for k in range(1, K + 1)])
    return env.cache[key]


def block_mean_share(L, tau):
    """Variance of the mean over a window of length L of a Gauss-Markov process with correlation
    time tau, per unit process variance: 2 (e^-u - 1 + u) / u^2, u = L / tau (the blocks'
    apparent hard iron, in the variogram view; what the norm channel's block means take is
    :func:`_block_mean_share_norm`)."""
    u = np.maximum(np.asarray(L, dtype=float) / np.asarray(tau, dtype=float), 1e-9)
    return np.where(u < 1e-4, 1.0 - u / 3.0, 2.0 * (np.exp(-u) - 1.0 + u) / (u * u))


def _within_block_excess(env, samples, mult, wide=None):
    """(lags s, excess, replica sd, pc, sigma) of the norm residual's lag
    autocovariance within blocks (each block's mean removed), over the replicas', lags 0..K;
    samples from :func:`_noise_samples`; the sd from the replicas of ``wide`` when given."""
    frame, base = env.frame, env.base
    slices = [sl for sl, w in zip(frame.block_slices(), mult) if w > 0]
    Lb = min(sl.stop - sl.start for sl in slices)
    K = int(max(4, min(200, Lb // 3)))
    sig = base.sigma[0]
    real, reps_in = samples
    s, c = _acov(real[0] / sig, real[1], slices, K)
    def rep_acov(pairs):
        out = []
        for z, inl in pairs:
            sr, cr = _acov(z / sig, inl, slices, K)
            out.append(sr / np.maximum(cr, 1))
        return np.array(out)
    reps = rep_acov(reps_in)
    if reps.shape[0] < 3:
        return None
    pc = np.concatenate([[1.0], np.maximum(_projection_acov(env, K), 1e-3)])
    ex = s / np.maximum(c, 1) - reps.mean(axis=0)
    sd = np.maximum((reps if wide is None else rep_acov(wide[1])).std(axis=0, ddof=1), 1e-9)
    return np.arange(K + 1) * frame.dt0, ex, sd, pc, sig


NOISE_CUT = 4.0             # robust scales: where the noise estimators stop reading the residual


def _noise_samples(env, ctx):
    """The norm residual of the recording and of each replica, (e, mask) pairs, as the noise
    estimators read them: the valid samples within NOISE_CUT robust scales of that data set's
    own residual (the same rule for each). Not the panel's 4 sigma of the baseline's white core:
    a slow noise a few times that core crosses it at its peaks (14% of the samples for 0.28 uT
    against 0.094 uT), and what is left of it is biased towards zero (on 8 simulated
    recordings of 0.11-0.30 uT its amplitude came out 7-45% low). Bursts, many sigma out, are
    still cut; so are, in the replicas, the bursts that the baseline made of such a noise's
    peaks."""
    sig = float(env.base.sigma[0])

    def cut(e, ok):
        scale = robust_sd(e[ok])
        return e, ok & (np.abs(e) < NOISE_CUT * max(sig, scale if np.isfinite(scale) else 0.0))
    real = cut(ctx.e[:, 0], ctx.valid[:, 0])
    reps = [cut(ctx.rep_e[i, :, 0], ctx.rep_valid[i, :, 0]) for i in range(ctx.rep_e.shape[0])]
    return real, reps


def _offsets(env, e, mask):
    """Apparent hard-iron offset (raw unit) of each block: the norm residual e (samples in mask)
    regressed on the time family's six regressors (1, v, v_x^2 - 1/3, v_y^2 - 1/3), as in
    :func:`block_offsets`."""
    if "time_regressors" not in env.cache:
        env.cache["time_regressors"] = time_regressors(env.base.fit.v)
    P = env.cache["time_regressors"]
    out = np.full((env.frame.n_blocks, 3), np.nan)
    used, A, r = [], [], []
    for b, sl in enumerate(env.frame.block_slices()):
        m = mask[sl]
        n = int(m.sum())
        if n < 30:
            continue
        X = P[sl][m]
        used.append(b)
        A.append(X.T @ X + 1e-3 * n * np.eye(6))    # the panel's ridge (:func:`.panel._solve6`)
        r.append(X.T @ e[sl][m])
    if used:                                        # one stacked solve (the same LAPACK calls)
        out[used] = np.linalg.solve(np.stack(A), np.stack(r)[..., None])[:, 1:4, 0]
    return out @ np.linalg.inv(env.base.fit.state.S).T


def _variogram(o, mult, kmax):
    """Mean squared change of the block offsets o (B, 3) at block lags 1..kmax (blocks in mult)."""
    ok = (mult > 0) & np.isfinite(o).all(axis=1)
    g = np.full(kmax, np.nan)
    for k in range(1, min(kmax, len(o) - 1) + 1):
        pair = ok[:-k] & ok[k:]
        if pair.any():
            g[k - 1] = np.mean(np.sum((o[k:][pair] - o[:-k][pair]) ** 2, axis=1))
    return g


def _variogram_excess(env, samples, mult, wide=None, kmax=8):
    """(block lags, excess, replica sd) of the variogram of the blocks' apparent hard iron;
    samples from :func:`_noise_samples`; the sd from the replicas of ``wide`` when given."""
    real, reps = samples
    g = _variogram(_offsets(env, *real), mult, kmax)
    gr = np.array([_variogram(_offsets(env, *r), mult, kmax) for r in reps])
    if gr.shape[0] < 3 or not np.isfinite(gr).all() or not np.isfinite(g).all():
        return None
    gs = gr if wide is None else np.array([_variogram(_offsets(env, *r), mult, kmax) for r in wide[1]])
    if not np.isfinite(gs).all():
        return None
    return np.arange(1, kmax + 1), g - gr.mean(axis=0), np.maximum(gs.std(axis=0, ddof=1), 1e-30)


def _colored():
    def replica(env, p):
        return [(EFFECTS["colored_noise"], {"sigma": s_, "tau": t_}) for s_, t_ in p["components"] if s_ > 0]

    def mag(env, p):
        comps = p["components"]
        val, unit = env.field_unit(float(np.sqrt(sum(s_ ** 2 for s_, _ in comps))))
        return {"value": val, "unit": unit, "components": [list(c) for c in comps],
                "meaning": "standard deviation per axis (Gauss-Markov components: [sigma, tau s])"}
    return EstimatedForm("colored_noise", "noise", _colored_fit, replica, mag, refine=_colored_refined)


def block_offsets(env, bs):
    """Apparent hard-iron offset (raw unit) of each block from the time-family regression."""
    from .panel import _solve6

    coef = _solve6(bs["tXX"][0], bs["tXe"][0])[:, 1:4] * env.base.sigma[0]
    return coef @ np.linalg.inv(env.base.fit.state.S).T


def _walk_stat(env, bs, mult):
    o = block_offsets(env, bs)
    tr = np.flatnonzero(mult > 0)
    pairs = [(a, b) for a, b in zip(tr[:-1], tr[1:]) if np.isfinite(o[a]).all() and np.isfinite(o[b]).all()]
    if not pairs:
        return np.nan, 0
    d = np.array([np.sum((o[b] - o[a]) ** 2) for a, b in pairs])
    gaps = np.array([b - a for a, b in pairs])
    return float(np.mean(d)), float(np.mean(gaps))


def _walk_estimate(env, ctx, mult):
    D, gap = _walk_stat(env, ctx.real_bs, mult)
    Dr = np.array([_walk_stat(env, bs, mult)[0] for bs in ctx.rep_bs])
    Dr = Dr[np.isfinite(Dr)]
    if not np.isfinite(D) or Dr.size < 3:
        return None
    ex = D - Dr.mean()
    if not ex > 3 * Dr.std(ddof=1):
        return None
    L = env.frame.duration / env.frame.n_blocks
    q2 = ex / (3.0 * (gap - 1.0 / 3.0) * L)           # per axis, unit^2/s (block means gap*L apart)
    return {"q": float(np.sqrt(q2) * 60.0)}           # unit/sqrt(h)


def _walk():
    def replica(env, p):
        return [(EFFECTS["bias_random_walk"], {"q": p["q"]})]

    def mag(env, p):
        val, unit = env.field_unit(p["q"])
        return {"value": val, "unit": unit + "/sqrt(h)"}
    return EstimatedForm("bias_random_walk", "noise", _walk_estimate, replica, mag)


def _quant_estimate(env, ctx, mult):
    lat = env.base.lattice
    if not np.nanmax(lat["strength"]) > 0.5:
        return None
    return {"q": lat["q"].tolist(), "phase": lat["phase"].tolist(), "lsb": float(np.nanmedian(lat["q"]))}


def _quant():
    def replica(env, p):
        q, ph = np.asarray(p["q"]), np.asarray(p["phase"])

        def fn(ctx):
            ok = np.isfinite(q) & (q > 0)
            ctx.m[:, ok] = np.round((ctx.m[:, ok] - ph[ok]) / q[ok]) * q[ok] + ph[ok]
        return [(_Custom("quantization", "range", fn), {})]

    def mag(env, p):
        val, unit = env.field_unit(p["lsb"])
        return {"value": val, "unit": unit, "meaning": "least significant bit"}
    return EstimatedForm("quantization", "noise", _quant_estimate, replica, mag)


def _sat_tol(env):
    q = np.nan_to_num(env.base.lattice["q"], nan=0.0) * (env.base.lattice["strength"] > 0.5)
    return np.maximum(0.5 * env.base.sigma_axis, 0.51 * q)


def _sat_estimate(env, ctx, mult):
    m = env.frame.m[np.isin(env.frame.block, np.flatnonzero(mult > 0))]
    tol = _sat_tol(env)
    levels = []
    for j in range(3):
        for sign in (1.0, -1.0):
            x = sign * m[:, j]
            top = x.max()
            n_at = int(np.sum(x >= top - tol[j]))
            n_band = int(np.sum((x < top - tol[j]) & (x >= top - 4 * tol[j])))
            if n_at >= max(8, 0.002 * m.shape[0]) and n_at > 2 * n_band:
                levels.append((j, sign, float(sign * top)))
    if not levels:
        return None
    return {"levels": levels, "limit": float(np.median([abs(L) for _, _, L in levels]))}


def _sat():
    def replica(env, p):
        def fn(ctx):
            for j, sign, L in p["levels"]:
                if sign > 0:
                    np.minimum(ctx.m[:, j], L, out=ctx.m[:, j])
                else:
                    np.maximum(ctx.m[:, j], L, out=ctx.m[:, j])
        return [(_Custom("saturation", "range", fn), {})]

    def mask(env, p, raw):
        tol = _sat_tol(env)
        ok = np.ones(raw.shape[0], dtype=bool)
        for j, sign, L in p["levels"]:
            ok &= ~(np.abs(raw[:, j] - L) <= tol[j])
        return ok

    def mag(env, p):
        val, unit = env.field_unit(p["limit"])
        return {"value": val, "unit": unit, "levels": [[j, s, env.field_unit(L)[0]] for j, s, L in p["levels"]]}
    return EstimatedForm("saturation", "mask", _sat_estimate, replica, mag, mask=mask)


def _clock_sums(bs, mult):
    return bs["clock"] @ mult


def _jitter_estimate(env, ctx, mult):
    """RMS from the variance of the time steps above the replicas' (a step is the difference of
    two independent errors: twice their variance); the shape from the steps' excess kurtosis
    (half that of the errors)."""
    ck = _clock_sums(ctx.real_bs, mult)
    n = max(ck[0], 1)
    v = ck[2] / n
    vr = np.array([(lambda c: c[2] / max(c[0], 1))(_clock_sums(bs, mult)) for bs in ctx.rep_bs])
    ex = v - vr.mean()
    se = max(vr.std(ddof=1) if vr.size > 2 else 0.0, v * np.sqrt(2.0 / n))
    if not ex > 3 * se or not ex > 1e-8:
        return None
    mu = ck[7] / n
    m2 = v - mu * mu
    m4 = ck[6] / n - 4 * mu * (ck[2] / n) * mu + 6 * mu * mu * v - 3 * mu ** 4  # central 4th moment (approx.)
    kd = m4 / max(m2 * m2, 1e-300) - 3.0
    return {"sigma": float(np.sqrt(ex / 2.0) * env.frame.dt0 * 1e3), "kurtosis": float(np.clip(2.0 * kd, 0.0, 20.0))}


def _drops_estimate(env, ctx, mult):
    ck = _clock_sums(ctx.real_bs, mult)
    lost, events = ck[3], ck[5]
    if lost < 1:
        return None
    steps = ck[0] + ck[3] + ck[4]
    return {"fraction": float(lost / max(steps + lost, 1)), "run": float(lost / max(events, 1))}


def _jitter():
    return EstimatedForm("timestamp_jitter", "clock", _jitter_estimate,
                         lambda env, p: [(EFFECTS["timestamp_jitter"],
                                          {"sigma": p["sigma"], "kurtosis": p["kurtosis"]})],
                         lambda env, p: {"value": p["sigma"], "unit": "ms", "meaning": "RMS timestamp error"})


def _drops():
    return EstimatedForm("sample_drops", "clock", _drops_estimate,
                         lambda env, p: [(EFFECTS["sample_drops"], {"fraction": p["fraction"], "run": p["run"]})],
                         lambda env, p: {"value": p["fraction"], "unit": "fraction", "run": p["run"]})


FORMS = {f.name: f for f in (
    _temp_offset(), _temp_scale(), _current(), _throttle(), _drift(), _step(), _walk(), _nonlin(), _sat(),
    MeanForm("cross_axis", lambda env: [{}], _rotation_G, 3, _rotation_mag, alias_of="misalignment"),
    _higher_order(), _quant(), _colored(), _latency(), _jitter(), _drops(), _hysteresis(),
    MeanForm("misalignment", lambda env: [{}], _rotation_G, 3, _rotation_mag),
)}

assert set(FORMS) == set(EFFECTS), set(FORMS) ^ set(EFFECTS)
