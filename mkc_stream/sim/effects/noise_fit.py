"""The statistics the noise forms read from the diagnoser's blocks: the coloured-noise estimator
and the per-block apparent hard iron (its variogram, the random walk's block-to-block wander).

Why apart from noise.py and drift.py: these are the estimators' numerics (autocovariances over
blocks, variograms, the shares of a Gauss-Markov noise that block means and the baseline's
white-noise estimate take), shared by coloured_noise and bias_random_walk; the effects declare
their forms beside their forward models and call into here. ``env`` is the diagnoser's view of
the recording (see :mod:`.form`).
"""
from __future__ import annotations

import itertools

import numpy as np


def _acov(z, inl, slices, K):
    """Sum of lag products and pair counts at lags 0..K over the given blocks (FFT per block)."""
    return _acov_sum([_acov_block(z[sl], inl[sl], K) for sl in slices], K)


def _acov_block(x, inl, kmax):
    """One block's lag products and pair counts at lags 0..min(kmax, L - 1), its mean removed;
    None for a block of fewer than 10 samples in ``inl``."""
    x = np.where(inl, x, 0.0)
    msk = inl.astype(float)
    if msk.sum() < 10:
        return None
    x = np.where(inl, x - x.sum() / msk.sum(), 0.0)
    L = x.size
    nf = 1 << int(np.ceil(np.log2(2 * L)))
    fx = np.fft.rfft(x, nf)
    fm = np.fft.rfft(msk, nf)
    kk = min(kmax, L - 1)
    return np.fft.irfft(fx * np.conj(fx), nf)[:kk + 1], np.fft.irfft(fm * np.conj(fm), nf)[:kk + 1]


def _acov_sum(blocks, K):
    """:func:`_acov` from per-block :func:`_acov_block` results (lags up to at least K each)."""
    s = np.zeros(K + 1)
    c = np.zeros(K + 1)
    for b in blocks:
        if b is None:
            continue
        kk = min(K, b[0].size - 1)
        s[:kk + 1] += b[0][:kk + 1]
        c[:kk + 1] += b[1][:kk + 1]
    return s, np.round(c)


#: the longest lag :func:`_within_block_excess` reads
ACOV_MAX_LAG = 200


class _Samples:
    """One data set's norm residual ``e`` and the samples the noise estimators read (``ok``,
    :func:`_noise_samples`), with what they derive from it block by block: the bootstrap's
    resamples (:meth:`mkc_stream.diagnose.attribution.Attribution._estimated_ci`) read the same
    residuals under 40 block weightings."""

    def __init__(self, e, ok):
        self.e, self.ok = e, ok
        self._blocks = self._offsets = None

    def acov_blocks(self, env, sig):
        """:func:`_acov_block` of every block of z = e / sig, lags to ACOV_MAX_LAG."""
        if self._blocks is None:
            z = self.e / sig
            self._blocks = [_acov_block(z[sl], self.ok[sl], ACOV_MAX_LAG) for sl in env.frame.block_slices()]
        return self._blocks

    def offsets(self, env):
        if self._offsets is None:
            self._offsets = _offsets(env, self.e, self.ok)
        return self._offsets


COLORED_GRID = 40           # correlation times tried, up to COLORED_SLOWEST blocks
COLORED_SLOWEST = 64
COLORED_FASTEST = 3         # samples: the refined grid's fastest (a faster one is the white noise's business)
COLORED_COMPONENTS = 3      # refined: a flicker-like noise spans three decades


def colored_fit(env, ctx, mult, spread=None, refined=False):
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
    baseline's replicas. Refined (:attr:`.form.EstimatedForm.refine`, chosen against the first by
    the gap index in :meth:`mkc_stream.diagnose.engine.Engine._refined`):

    * three components: a flicker-like noise spans decades (two fitted to sums of 0.5, 5 and
      30 s left a gap index of 1.6-1.7 on benchmark trials the true three closed to 1.3);
    * ``spread``, an evaluation whose replicas carry a previous estimate, gives the points' sd:
      the baseline's replicas hold white noise only (1e-4 uT^2 at a lag), while a slow noise's
      own realisation moves the long lags and the variogram by 30-50 of those sd, so the first
      fit follows one realisation's accidents (the excess is still over the baseline's replicas);
    * the baseline's white noise (third differences) already holds h(tau) of each component
      (:func:`colored_white_share`): taken off the model's lag 0, and off the replicas' white
      noise (:meth:`mkc_stream.diagnose.engine.Engine._norm`, flagged by "white_share");
    * the grid starts at COLORED_FASTEST samples (a one-sample component stands for white noise).
    """
    from scipy.optimize import nnls      # here: simulating needs no optimiser

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


def colored_refined(env, ctx, mult, spread):
    return colored_fit(env, ctx, mult, spread, refined=True)


def colored_white_share(dt, tau):
    """Share of a Gauss-Markov noise's variance that the baseline's white-noise estimate (third
    differences, :func:`mkc_stream.diagnose.baseline.hf_sigma`) reads as white: var(d3 x) / (20 var x) for an AR(1)
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

    key = ("bshare", round(float(tau), 9))
    if key not in env.cache:            # per block, for every block weighting
        JS = env.base.fit.v @ env.base.fit.state.S
        rho = float(np.exp(-env.frame.dt0 / tau))
        per_block = []
        for sl in env.frame.block_slices():
            if sl.stop - sl.start < 2:
                per_block.append(np.nan)
                continue
            X = JS[sl]
            fwd = lfilter([1.0], [1.0, -rho], X, axis=0)
            bwd = lfilter([1.0], [1.0, -rho], X[::-1], axis=0)[::-1]
            per_block.append(np.sum(X * (fwd + bwd - X)) / X.shape[0] ** 2)
        env.cache[key] = np.array(per_block)
    per_block = env.cache[key]
    n = min(per_block.size, len(mult))
    vals = per_block[:n][(np.asarray(mult)[:n] > 0) & np.isfinite(per_block[:n])]
    return float(np.mean(vals)) if vals.size else 0.0


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
    slices = frame.block_slices()
    sel = [b for b, (_, w) in enumerate(zip(slices, mult)) if w > 0]
    Lb = min(slices[b].stop - slices[b].start for b in sel)
    K = int(max(4, min(ACOV_MAX_LAG, Lb // 3)))
    sig = base.sigma[0]
    real, reps_in = samples

    def acov(smp):
        blocks = smp.acov_blocks(env, sig)
        return _acov_sum([blocks[b] for b in sel], K)
    s, c = acov(real)

    def rep_acov(sets):
        out = []
        for smp in sets:
            sr, cr = acov(smp)
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
    arrays = (ctx.e, ctx.valid, ctx.rep_e, ctx.rep_valid)
    kept = env.cache.setdefault("noise_samples", {})
    hit = kept.get(id(ctx))
    if hit is not None and all(a is b for a, b in zip(hit[0], arrays)):
        return hit[1]
    sig = float(env.base.sigma[0])

    def cut(e, ok):
        scale = env.robust_sd(e[ok])
        return _Samples(e, ok & (np.abs(e) < NOISE_CUT * max(sig, scale if np.isfinite(scale) else 0.0)))
    real = cut(ctx.e[:, 0], ctx.valid[:, 0])
    reps = [cut(ctx.rep_e[i, :, 0], ctx.rep_valid[i, :, 0]) for i in range(ctx.rep_e.shape[0])]
    if len(kept) >= 4:                  # a few evaluations' worth (each holds R + 1 residuals)
        kept.clear()
    kept[id(ctx)] = (arrays, (real, reps))
    return real, reps


def _offsets(env, e, mask):
    """Apparent hard-iron offset (raw unit) of each block: the norm residual e (samples in mask)
    regressed on the time family's six regressors (1, v, v_x^2 - 1/3, v_y^2 - 1/3), as in
    :func:`block_offsets`."""
    P = env.time_regressors()
    out = np.full((env.frame.n_blocks, 3), np.nan)
    used, A, r = [], [], []
    for b, sl in enumerate(env.frame.block_slices()):
        m = mask[sl]
        n = int(m.sum())
        if n < 30:
            continue
        X = P[sl][m]
        used.append(b)
        A.append(X.T @ X + 1e-3 * n * np.eye(6))    # the panel's ridge (``env.solve6``)
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
    g = _variogram(real.offsets(env), mult, kmax)
    gr = np.array([_variogram(r.offsets(env), mult, kmax) for r in reps])
    if gr.shape[0] < 3 or not np.isfinite(gr).all() or not np.isfinite(g).all():
        return None
    gs = gr if wide is None else np.array([_variogram(r.offsets(env), mult, kmax) for r in wide[1]])
    if not np.isfinite(gs).all():
        return None
    return np.arange(1, kmax + 1), g - gr.mean(axis=0), np.maximum(gs.std(axis=0, ddof=1), 1e-30)


def block_offsets(env, bs):
    """Apparent hard-iron offset (raw unit) of each block from the time-family regression."""
    coef = env.solve6(bs["tXX"][0], bs["tXe"][0])[:, 1:4] * env.base.sigma[0]
    return coef @ np.linalg.inv(env.base.fit.state.S).T

