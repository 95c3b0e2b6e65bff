"""Per-block sufficient statistics of one recording (real or replica), from which
:func:`.panel.evaluate` builds the panel for any weighting of the blocks: counts, moments and
histograms of the standardised residual per block and direction cell, the time family's
regression sums per block and aux bin, periodogram bands and Allan variances, the raw values'
lattice and pile-up, and the clock's steps.

Which samples count as inliers: those within 4 sigma, outside a burst's interior
(:func:`between_outliers`) and outside the bursts no sample of which is an outlier
(:func:`.baseline.hidden_bursts`).
"""
from __future__ import annotations

import numpy as np

from .baseline import hidden_bursts
from .panel import BAND_FRACTIONS, HIST_EDGES, N_AUX_BINS, N_HIST, TAUS, PanelDesign
from .panel_sums import group_sums, regression_sums

#: samples: outliers this close are one burst (see :func:`between_outliers`)
BURST_GAP = 10


def _bc(idx, w, size):
    return np.bincount(idx, weights=w, minlength=size)


def groupings(d: PanelDesign) -> dict:
    """Each sample's group (-1: none) for :mod:`.panel_sums`, as (N, Q) columns: ``block``;
    ``moments`` [block, block x direction cell]; ``regression`` [block, block x bin of each aux
    signal]."""
    if getattr(d, "_groups", None) is None:
        blk = np.asarray(d.block, dtype=np.int64)
        reg = [blk] + [np.where(bins >= 0, blk * N_AUX_BINS + bins, -1) for bins in d.aux_bins.values()]
        cols = {"block": [blk], "moments": [blk, blk * d.n_cells + d.cell], "regression": reg}
        d._groups = {k: np.ascontiguousarray(np.stack(v, axis=1), dtype=np.int64) for k, v in cols.items()}
    return d._groups


def between_outliers(out, gap=BURST_GAP):
    """(N, C) samples that are not outliers but lie between two outliers at most ``gap`` samples
    apart: a burst's interior. A burst's norm residual crosses zero wherever its offset turns
    perpendicular to the field, and those samples, kept as inliers, shifted the block means and
    regressions of a recording with bursts (z 5-7 on nulls) by where its bursts happened to be.
    Two 4-sigma outliers of white noise fall that close about once in 10^7 samples."""
    n = out.shape[0]
    idx = np.arange(n)[:, None]
    far = n + 2 * gap + 2
    prev = np.maximum.accumulate(np.where(out, idx, -far), axis=0)
    nxt = np.minimum.accumulate(np.where(out, idx, n + far)[::-1], axis=0)[::-1]
    return (nxt - prev <= gap) & ~out


def recorded_stats(d: PanelDesign, raw, clock_t=None) -> dict:
    """The per-block sums that depend on the raw values and the clock only, not on a fit's
    residual (the ``raw`` and ``timing`` families): a replica's are the same for every
    candidate model scored on it."""
    s = {}
    _raw(d, s, raw)
    _timing(d, s, clock_t)
    return s


def block_stats(d: PanelDesign, e, valid, raw, clock_t=None, recorded=None) -> dict:
    """Per-block sufficient statistics of one recording (real or replica). recorded: its
    :func:`recorded_stats` when already computed (else from ``raw`` and ``clock_t``)."""
    B, C, K = d.n_blocks, d.C, d.n_cells
    groups = groupings(d)
    z = e / d.sigma[None, :]
    far = valid & ~(np.abs(z) < 4.0)
    inl = valid & ~far & ~between_outliers(far)
    # a burst whose offset lies almost across the field has no 4-sigma sample; the scan flags it
    # in the norm channel alike in the recording and in every replica
    far[:, 0] |= hidden_bursts(z[:, 0], inl[:, 0])
    inl = valid & ~far & ~between_outliers(far)
    out = valid & ~inl
    zi = np.where(inl, z, 0.0)
    fi = inl.astype(float)
    fv = valid.astype(float)
    s = {}
    hidx = np.clip(np.searchsorted(HIST_EDGES, z, side="right"), 0, N_HIST - 1)
    s["hist"] = np.stack([_bc(d.block * N_HIST + hidx[:, c], fv[:, c], B * N_HIST)
                          .reshape(B, N_HIST) for c in range(C)])
    # per-group sums (panel_sums): counts and moments [inl, z, z^2, valid, out] per channel to
    # blocks and cells; the regression sums [PP*inl (21), P*z (6)] per channel to blocks and aux
    # bins (cells never use them: they would be a third of the work for nothing)
    N = z.shape[0]
    W = np.empty((N, 5 * C))
    for c in range(C):
        W[:, 5 * c] = fi[:, c]
        W[:, 5 * c + 1] = zi[:, c]
        W[:, 5 * c + 2] = zi[:, c] ** 2
        W[:, 5 * c + 3] = fv[:, c]
        W[:, 5 * c + 4] = out[:, c]
    Wg = group_sums(groups["moments"], B * K, W)
    Wb = Wg[0, :B]                                   # (B, 5 C)
    Wk = Wg[1].reshape(B, K, 5 * C)
    Rg = regression_sums(groups["regression"], B * N_AUX_BINS, d.PP, d.P, fi, zi)
    Rb = Rg[0, :B].reshape(B, 27 * C)                # (B, 27 C)
    s["n"], s["s1"], s["s2"], s["nvalid"], s["out"] = (Wb[:, k::5].T.copy() for k in range(5))
    s["tXX"] = np.stack([Rb[:, 27 * c: 27 * c + 21] for c in range(C)])
    s["tXe"] = np.stack([Rb[:, 27 * c + 21: 27 * c + 27] for c in range(C)])
    s["cell_n"] = np.stack([Wk[..., 5 * c] for c in range(C)])
    s["cell_s"] = np.stack([Wk[..., 5 * c + 1] for c in range(C)])
    s["cell_valid"] = Wk[..., 3].copy()
    s["cell_out"] = Wk[..., 4].copy()
    for q, name in enumerate(d.aux_bins, start=1):
        A = Rg[q].reshape(B, N_AUX_BINS, 27 * C)
        s["aXX:" + name] = np.stack([A[..., c * 27: c * 27 + 21] for c in range(C)])
        s["aXe:" + name] = np.stack([A[..., c * 27 + 21: c * 27 + 27] for c in range(C)])
    if d.rot is not None and C == 2:
        rr = np.empty((N, 9))
        for k, (i, j) in enumerate((i, j) for i in range(3) for j in range(i, 3)):
            np.multiply(d.rot[:, i], d.rot[:, j] * fi[:, 1], out=rr[:, k])
        np.multiply(d.rot, zi[:, 1:2], out=rr[:, 6:])
        Wr = group_sums(groups["block"], B, rr)[0]
        s["rXX"], s["rXe"] = Wr[:, :6], Wr[:, 6:]
    if d.quart is not None:
        qz = np.empty((N, 6))
        np.multiply(d.quart, zi[:, :1], out=qz[:, :3])
        np.multiply(d.quart ** 2, fi[:, :1], out=qz[:, 3:])
        Wq = group_sums(groups["block"], B, qz)[0]
        s["qe"], s["qq"] = Wq[:, :3], Wq[:, 3:]
    _spectral(d, s, zi, inl)
    s.update(recorded_stats(d, raw, clock_t) if recorded is None else recorded)
    return s


def _spectral(d, s, zi, inl):
    """Octave-band periodogram, Allan variance and third-difference noise, per block.

    All blocks are cut to the shortest block's length so one FFT covers them all.
    """
    B, C = d.n_blocks, d.C
    nb = BAND_FRACTIONS.size - 1
    lens = np.array([sl.stop - sl.start for sl in d.slices])
    L = int(lens[lens > 0].min()) if (lens > 0).any() else 0
    spec = np.zeros((C, B, nb))
    spec_n = np.zeros((C, B, nb))
    av = np.zeros((C, B, len(TAUS)))
    av_n = np.zeros((C, B, len(TAUS)))
    # third differences within blocks
    d3 = zi[3:] - 3 * zi[2:-1] + 3 * zi[1:-2] - zi[:-3]
    good = inl[3:] & inl[2:-1] & inl[1:-2] & inl[:-3] & (d.block[3:] == d.block[:-3])[:, None]
    hf = np.stack([_bc(d.block[3:], np.where(good[:, c], d3[:, c] ** 2, 0.0) / 20.0, B) for c in range(C)])
    hf_n = np.stack([_bc(d.block[3:], good[:, c].astype(float), B) for c in range(C)])
    if L >= 16:
        ok_b = lens >= L
        starts = np.array([sl.start for sl in d.slices])
        idx = starts[:, None] + np.arange(L)[None, :]
        idx[~ok_b] = 0
        x = zi[idx]                               # (B, L, C)
        m = inl[idx]
        cnt = np.maximum(m.sum(axis=1, keepdims=True), 1)
        x = np.where(m, x - x.sum(axis=1, keepdims=True) / cnt, 0.0)
        x[~ok_b] = 0.0
        P = np.abs(np.fft.rfft(x, axis=1)) ** 2 / L     # (B, F, C)
        f = np.arange(P.shape[1]) / L * 2.0
        band = np.searchsorted(BAND_FRACTIONS, f, side="right") - 1
        for k in range(nb):
            sel = (band == k) & (f > 0)
            if sel.any():
                spec[:, :, k] = P[:, sel, :].sum(axis=1).T
                spec_n[:, :, k] = sel.sum() * ok_b
        for i, tau in enumerate(TAUS):
            k = L // tau
            if k < 4:
                continue
            # the mean over tau as a running sum of slices: the same additions in the same
            # order as .mean(axis=2), a third of its time (strided reductions are slow)
            xr = x[:, :k * tau].reshape(B, k, tau, C)
            means = xr[:, :, 0, :].copy()
            for j in range(1, tau):
                means += xr[:, :, j, :]
            means /= tau
            dm = np.diff(means, axis=1)
            av[:, :, i] = (0.5 * np.sum(dm * dm, axis=1)).T * ok_b
            av_n[:, :, i] = (k - 1) * ok_b
    s.update(spec=spec, spec_n=spec_n, avar=av, avar_n=av_n, hf=hf, hf_n=hf_n)


def _raw(d, s, raw):
    B = d.n_blocks
    ph = 2 * np.pi * (raw - d.lattice_phase) / d.lattice_q
    cols = np.empty((raw.shape[0], 12))          # cos, sin of the lattice phase; at max, at min
    for j in range(3):          # column by column as before: numpy's SIMD paths may differ by layout
        cols[:, j] = np.cos(ph[:, j])
        cols[:, 3 + j] = np.sin(ph[:, j])
    cols[:, 6:9] = raw >= raw.max(axis=0) - d.pile_tol
    cols[:, 9:12] = raw <= raw.min(axis=0) + d.pile_tol
    # contiguous (12, B): einsum sums a strided view in another order (last-bit changes)
    sums = np.ascontiguousarray(group_sums(groupings(d)["block"], B, cols)[0].T)
    s["lat_c"], s["lat_s"] = sums[0:3], sums[3:6]
    s["raw_n"] = np.bincount(d.block, minlength=B).astype(float)
    s["pile"] = np.stack([sums[[6 + j, 9 + j]] for j in range(3)])


def _timing(d, s, t):
    B = d.n_blocks
    z = np.zeros((8, B))
    if t is not None and len(t) > 2:
        dt = np.diff(t) / d.dt0
        blk = np.clip(np.searchsorted(d.block_edges_t, t[1:], side="right") - 1, 0, B - 1)
        normal = (dt > 0.5) & (dt < 1.5)
        z[0] = _bc(blk, normal.astype(float), B)
        z[1] = _bc(blk, np.where(normal, np.abs(dt - 1.0), 0.0), B)
        z[2] = _bc(blk, np.where(normal, (dt - 1.0) ** 2, 0.0), B)
        z[3] = _bc(blk, np.where(dt >= 1.5, np.round(dt) - 1.0, 0.0), B)
        z[4] = _bc(blk, (dt <= 0.5).astype(float), B)
        z[5] = _bc(blk, (dt >= 1.5).astype(float), B)
        z[6] = _bc(blk, np.where(normal, (dt - 1.0) ** 4, 0.0), B)
        z[7] = _bc(blk, np.where(normal, dt - 1.0, 0.0), B)
    s["clock"] = z
