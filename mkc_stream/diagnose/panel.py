"""The fixed panel of statistics on which real and simulated recordings are compared.

Each statistic is built from per-block sufficient statistics (sums, counts, small normal
matrices, periodogram band sums), so the same panel is evaluated on all blocks, on held-out
blocks only, or on a bootstrap resample of blocks by a weighted sum, without touching the
samples again. Families (``where`` in the JSON):

* ``distribution`` per channel: mean, RMS over high-frequency noise, IQR, tails beyond 3 and 5
  sigma, quantile skewness and kurtosis;
* ``sphere``: mean residual in 18 equal-area direction cells;
* ``time``: per block, the residual regressed on [1, v, vx^2 - 1/3, vy^2 - 1/3] (v the calibrated
  direction): the block's apparent offset, hard-iron change and soft-iron change;
* ``changes``: how that apparent hard iron moves from block to block (largest jump over the
  median one; von Neumann ratio): a step, a drift and a random walk differ here;
* ``aux:NAME``: the same regression per quantile bin of each aux signal (and the turn rate);
* ``frequency``: periodogram power in octave bands and the Allan variance at 1-32 samples;
* ``quartic``: the norm residual's correlation with the fourth power of each raw axis's
  direction cosine, u_j^4, after removing what any ellipsoid absorbs (degree <= 2 in the
  calibrated direction): a per-axis scale nonlinearity (a cubic departure x_j^3 of each axis)
  leaves this degree-4 pattern in the field strength, which no hard/soft iron can fit, while the
  18 direction cells spread it thin;
* ``weights``: where the fit down-weighted samples (overall, per block, per direction cell);
* ``raw``: lattice strength of the raw values (quantization) and pile-up at the extremes (clipping);
* ``timing``: timestamp jitter, lost and doubled samples.

Residuals are scaled by a fixed sigma per channel (the real recording's), so every statistic
is dimensionless.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


HIST_EDGES = np.arange(-8.0, 8.0 + 1e-9, 0.25)
N_HIST = HIST_EDGES.size + 1            # + under/overflow
N_AUX_BINS = 6
BAND_FRACTIONS = np.array([1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0])   # of Nyquist
TAUS = (1, 2, 4, 8, 16, 32)
N_BANDS_Z, N_SECTORS = 3, 6
REG_NAMES = ("mean", "v_x", "v_y", "v_z", "aniso_x", "aniso_y")
_TRI = [(i, j) for i in range(6) for j in range(i, 6)]
_SYM6 = np.zeros((6, 6), dtype=np.intp)    # _SYM6[i, j]: the packed index of (min, max)
for _k, (_i, _j) in enumerate(_TRI):
    _SYM6[_i, _j] = _SYM6[_j, _i] = _k
CHANNEL_NAMES = ("norm", "dip")


def direction_cell(v: np.ndarray) -> np.ndarray:
    """18 equal-area cells: 3 bands in z x 6 sectors in longitude."""
    z = np.clip(v[:, 2], -1.0, 1.0)
    band = np.minimum(((z + 1.0) * 0.5 * N_BANDS_Z).astype(np.int64), N_BANDS_Z - 1)
    lon = np.arctan2(v[:, 1], v[:, 0]) + np.pi
    sector = np.minimum((lon / (2 * np.pi) * N_SECTORS).astype(np.int64), N_SECTORS - 1)
    return band * N_SECTORS + sector


def cell_label(c: int) -> str:
    band, sector = divmod(int(c), N_SECTORS)
    lat = ("south", "equator", "north")[band]
    return f"{lat} {sector * 60 - 180:+d}..{sector * 60 - 120:+d} deg"


@dataclass
class PanelDesign:
    block: np.ndarray
    n_blocks: int
    slices: list
    P: np.ndarray
    PP: np.ndarray
    cell: np.ndarray
    aux_bins: dict                  # name -> (N,) bin (-1 = none)
    aux_edges: dict                 # name -> bin edges (for labels)
    aux_centres: dict               # name -> (bins,) median aux value per bin, centred, per unit span
    sigma: np.ndarray               # (C,)
    dt0: float
    lattice_q: np.ndarray           # (3,)
    lattice_phase: np.ndarray       # (3,)
    pile_tol: np.ndarray            # (3,)
    block_edges_t: np.ndarray       # (B + 1,) times
    block_t0: np.ndarray            # (B,) start time of each block
    n_cells: int = N_BANDS_Z * N_SECTORS
    unit: str = "uT"
    aux_units: dict = field(default_factory=dict)
    rot: np.ndarray | None = None   # (N, 3) dip change per small rotation of the field against gravity (per sigma)
    quart: np.ndarray | None = None  # (N, 3) u_j^4 of the raw direction, orthogonal to degree <= 2 of v

    @property
    def C(self) -> int:
        return int(self.sigma.shape[0])


def quartic_basis(u_raw, v):
    """u_j^4 (raw-frame direction) minus its least-squares fit by 1, v and v v^T (what an
    ellipsoid absorbs), each column scaled to unit RMS."""
    Q = u_raw ** 4
    A = np.column_stack([np.ones(v.shape[0]), v] + [v[:, i] * v[:, j] for i in range(3) for j in range(i, 3)])
    Q = Q - A @ np.linalg.lstsq(A, Q, rcond=None)[0]
    return Q / np.maximum(np.sqrt(np.mean(Q * Q, axis=0)), 1e-12)


def time_regressors(v):
    """The time family's six regressors (REG_NAMES): 1, v, v_x^2 - 1/3, v_y^2 - 1/3."""
    return np.stack([np.ones(v.shape[0]), v[:, 0], v[:, 1], v[:, 2], v[:, 0] ** 2 - 1 / 3, v[:, 1] ** 2 - 1 / 3],
                    axis=1)


def make_design(frame, v, sigma, extra_aux: dict, lattice_q, lattice_phase, pile_tol, rot=None,
                u_raw=None) -> PanelDesign:
    P = time_regressors(v)
    PP = np.stack([P[:, i] * P[:, j] for i, j in _TRI], axis=1)
    bins, edges, centres = {}, {}, {}
    for name, x in list(frame.aux.items()) + list(extra_aux.items()):
        q = np.quantile(x, np.linspace(0, 1, N_AUX_BINS + 1))
        q = np.unique(q)
        if q.size < 3:
            continue
        bins[name] = np.clip(np.searchsorted(q, x, side="right") - 1, 0, q.size - 2)
        edges[name] = q
        med = np.array([np.median(x[bins[name] == k]) for k in range(q.size - 1)])
        centres[name] = (med - med.mean()) / max(np.ptp(med), 1e-12)
    T = frame.t
    edges_t = T[0] + frame.duration * np.arange(frame.n_blocks + 1) / frame.n_blocks
    return PanelDesign(block=frame.block, n_blocks=frame.n_blocks, slices=frame.block_slices(), P=P, PP=PP,
                       cell=direction_cell(v), aux_bins=bins, aux_edges=edges, aux_centres=centres,
                       sigma=np.asarray(sigma, float),
                       dt0=frame.dt0, lattice_q=np.asarray(lattice_q, float),
                       lattice_phase=np.asarray(lattice_phase, float), pile_tol=np.asarray(pile_tol, float),
                       block_edges_t=edges_t, block_t0=edges_t[:-1], unit=frame.unit, rot=rot,
                       quart=None if u_raw is None else quartic_basis(u_raw, v))


# ---------------------------------------------------------------------------------------------
# from block sums to the panel
# ---------------------------------------------------------------------------------------------

def _solve6(XX21, Xe):
    """Coefficients of the 6-regressor fit from packed X^T X (..., 21) and X^T e (..., 6)."""
    A = XX21[..., _SYM6]                          # (..., 6, 6), both triangles from the packed one
    n = A[..., 0, 0]
    ridge = 1e-3 * np.maximum(n, 1e-12)
    A = A + ridge[..., None, None] * np.eye(6)
    coef = np.linalg.solve(A, Xe[..., None])[..., 0]
    coef[n < 30] = np.nan
    return coef


def _quantiles(h, qs):
    """Quantiles (in sigma) from histograms (..., N_HIST) over HIST_EDGES with under/overflow bins."""
    c = np.cumsum(h, axis=-1)
    tot = c[..., -1:]
    target = np.asarray(qs, dtype=np.float64) * tot                       # (..., Q), all at once
    k = np.clip(np.sum(c[..., None, :] < target[..., None], axis=-1), 0, N_HIST - 1)
    prev = np.where(k > 0, np.take_along_axis(c, np.maximum(k - 1, 0), axis=-1), 0.0)
    hk = np.maximum(np.take_along_axis(h, k, axis=-1), 1e-12)
    lo = HIST_EDGES[np.clip(k - 1, 0, HIST_EDGES.size - 1)]
    val = lo + 0.25 * (target - prev) / hk
    val = np.where(k == 0, HIST_EDGES[0], np.where(k >= N_HIST - 1, HIST_EDGES[-1], val))
    val = np.where(tot > 0, val, np.nan)
    return [val[..., i] for i in range(len(qs))]


class Panel:
    """Values (M, K), weights (M, K), floors (M, K), families and labels of a panel evaluated for
    M block weightings at once (M = 1 for one weighting). Floors, weights and labels are built
    only when asked for: a replica's panel is read for its values alone."""

    def __init__(self, M):
        self.M = M
        self._parts = []            # (family, channel, labels, values (M, n), floors, weights)

    def add(self, family, channel, labels, values, floors, weights=1.0):
        values = np.asarray(values, dtype=np.float64).reshape(self.M, -1)
        self._parts.append((family, channel, [labels] if isinstance(labels, str) else labels, values, floors,
                            weights))

    @property
    def family(self) -> list:
        return [p[0] for p in self._parts for _ in range(p[3].shape[1])]

    @property
    def labels(self) -> list:
        return [(p[1], lab) for p in self._parts for lab in p[2]]

    def values(self) -> np.ndarray:
        return np.concatenate([p[3] for p in self._parts], 1)

    def _filled(self, k):
        """Floors (k = 4) or weights (k = 5) as (M, K): each part's scalar, per-statistic (n,) row
        or full (M, n) array."""
        out = np.empty((self.M, sum(p[3].shape[1] for p in self._parts)))
        i = 0
        for p in self._parts:
            n = p[3].shape[1]
            x = np.asarray(p[k], dtype=np.float64)
            out[:, i:i + n] = x if x.ndim == 0 or x.shape == (n,) else x.reshape(self.M, n)
            i += n
        return out

    def matrices(self):
        return self.values(), self._filled(5), self._filled(4)

    def arrays(self):
        v, w, f = self.matrices()
        return v[0], w[0], f[0]


def _binom_floor(p, n):
    n = np.maximum(n, 1.0)
    return np.sqrt(np.maximum(np.nan_to_num(p), 1.0 / n) / n)


def _labels(d: PanelDesign) -> dict:
    """The panel's labels that depend on the design only (built once: the panel is evaluated
    for every replica and bootstrap)."""
    if getattr(d, "_lab", None) is None:
        blab = [f"{d.block_t0[b]:.0f}-{d.block_edges_t[b + 1]:.0f} s" for b in range(d.n_blocks)]
        cells = [cell_label(k) for k in range(d.n_cells)]
        aux = {}
        for name in d.aux_bins:
            edges = d.aux_edges[name]
            labs = []
            for k in range(N_AUX_BINS):
                lab = f"{edges[k]:.3g}..{edges[k + 1]:.3g}" if k + 1 < edges.size else "-"
                labs += [f"{lab} {r}" for r in REG_NAMES]
            aux[name] = labs + [f"trend over its span: {r}" for r in REG_NAMES[:4]]
        d._lab = {"cells": cells, "time": [f"{bl} {r}" for bl in blab for r in REG_NAMES],
                  "weights_block": [f"down-weighted {bl}" for bl in blab],
                  "weights_cell": [f"down-weighted in {lab}" for lab in cells], "aux": aux}
    return d._lab


def evaluate(d: PanelDesign, s: dict, mult: np.ndarray) -> Panel:
    """The panel over blocks weighted by ``mult`` (B,) or (M, B) (1 = use once, 0 = leave out).
    Every statistic is a function of the block sums, so a bootstrap's resample reads the same
    statistics as the point estimate. (The MKC E-step's (sigma, d) of the norm residual is not
    one: once the tails are Gaussian its likelihood is flat in sigma and the E-step stops
    anywhere on the ridge; see docs/decisions/0028.)"""
    mult = np.atleast_2d(np.asarray(mult, dtype=np.float64))
    M = mult.shape[0]
    p = Panel(M)
    C = d.C
    ch = CHANNEL_NAMES
    lab = _labels(d)
    aggc = lambda x: np.einsum("cb...,mb->mc...", x, mult)  # noqa: E731  (channel, block, ...) -> (M, C, ...)
    agg = lambda x: np.einsum("b...,mb->m...", x, mult)     # noqa: E731
    # distribution
    H = aggc(s["hist"])                                     # (M, C, N_HIST)
    n, s1, s2 = aggc(s["n"]), aggc(s["s1"]), aggc(s["s2"])
    hf, hf_n = aggc(s["hf"]), aggc(s["hf_n"])
    q = _quantiles(H, (0.025, 0.10, 0.25, 0.5, 0.75, 0.90, 0.975))
    nall = np.maximum(H.sum(axis=-1), 1.0)
    i3lo, i3hi = np.searchsorted(HIST_EDGES, -3.0) + 1, np.searchsorted(HIST_EDGES, 3.0) + 1
    i5lo, i5hi = np.searchsorted(HIST_EDGES, -5.0) + 1, np.searchsorted(HIST_EDGES, 5.0) + 1
    t3 = (H[..., :i3lo].sum(-1) + H[..., i3hi:].sum(-1)) / nall
    t5 = (H[..., :i5lo].sum(-1) + H[..., i5hi:].sum(-1)) / nall
    nn = np.maximum(n, 1.0)
    var = np.maximum(s2 / nn - (s1 / nn) ** 2, 1e-12)
    hfv = np.maximum(hf / np.maximum(hf_n, 1.0), 1e-12)
    for c in range(C):
        p.add("distribution", ch[c], "mean", s1[:, c] / nn[:, c], 1e-3)
        p.add("distribution", ch[c], "rms / high-frequency noise", np.log(var[:, c] / hfv[:, c]) / 2, 1e-3)
        p.add("distribution", ch[c], "IQR", (q[4][:, c] - q[2][:, c]) / 1.349, 1e-3)
        p.add("distribution", ch[c], "beyond 3 sigma", t3[:, c], _binom_floor(t3[:, c], nall[:, c]))
        p.add("distribution", ch[c], "beyond 5 sigma", t5[:, c], _binom_floor(t5[:, c], nall[:, c]))
        p.add("distribution", ch[c], "skewness (quantile)",
              (q[5][:, c] + q[1][:, c] - 2 * q[3][:, c]) / np.maximum(q[5][:, c] - q[1][:, c], 1e-9), 1e-3)
        p.add("distribution", ch[c], "kurtosis (quantile)",
              (q[6][:, c] - q[0][:, c]) / np.maximum(q[4][:, c] - q[2][:, c], 1e-9), 1e-3)
    # sphere
    cn, cs = aggc(s["cell_n"]), aggc(s["cell_s"])        # (M, C, K)
    for c in range(C):
        p.add("sphere", ch[c], lab["cells"], np.where(cn[:, c] >= 20, cs[:, c] / np.maximum(cn[:, c], 1), np.nan), 1e-3)
    # time: per block regression, weighted by multiplicity
    coef = _solve6(s["tXX"], s["tXe"])          # (C, B, 6)
    wt = np.repeat(mult, 6, axis=1)
    for c in range(C):
        vals = np.where(wt > 0, coef[c].reshape(1, -1), np.nan)
        p.add("time", ch[c], lab["time"], vals, 1e-3, wt)
    # changes: how the block-wise apparent hard iron moves (a step jumps once, a drift moves
    # evenly, a random walk wanders, noise does not move at all)
    tc = d.block_t0 - d.block_t0.mean()
    tc = tc / max(np.abs(tc).max(), 1e-12)
    for c in range(C):
        jv = np.full((M, 6), np.nan)
        usable = (mult > 0) & np.isfinite(coef[c, :, :4]).all(axis=1)[None, :]     # (M, B)
        for m in range(M):
            used = np.flatnonzero(usable[m])
            if len(used) >= 6:
                o = coef[c, used, 1:4]
                dd = np.linalg.norm(np.diff(o, axis=0), axis=1)
                jv[m, 0] = np.log(dd.max() / max(np.median(dd), 1e-12))
                jv[m, 1] = np.log(np.sum(dd * dd) / max(np.sum((o - o.mean(axis=0)) ** 2), 1e-12))
                x = tc[used] - tc[used].mean()
                jv[m, 2:] = (x @ (coef[c, used, :4] - coef[c, used, :4].mean(axis=0))) / max(x @ x, 1e-12)
        p.add("changes", ch[c], ["largest / median block-to-block change of the apparent hard iron (log)",
                                 "von Neumann ratio of the apparent hard iron (log)",
                                 "trend of the mean residual over the recording", "trend of the apparent hard iron x",
                                 "trend of the apparent hard iron y", "trend of the apparent hard iron z"],
              jv, [0.01, 0.01, 1e-3, 1e-3, 1e-3, 1e-3])
    # alignment: the dip residual regressed on a small rotation of the field against gravity
    if "rXX" in s:
        XX = np.einsum("bk,mb->mk", s["rXX"], mult)
        Xe = np.einsum("bk,mb->mk", s["rXe"], mult)
        A = np.zeros((M, 3, 3))
        for k, (i, j) in enumerate((i, j) for i in range(3) for j in range(i, 3)):
            A[:, i, j] = A[:, j, i] = XX[:, k]
        A += 1e-9 * np.maximum(np.trace(A, axis1=1, axis2=2), 1e-12)[:, None, None] * np.eye(3)
        rot = np.linalg.solve(A, Xe[..., None])[..., 0]
        p.add("alignment", "dip", [f"apparent rotation against gravity {a}" for a in "xyz"], rot, 1e-4)
    # quartic: the degree-4 pattern of a per-axis scale nonlinearity (normalised correlation)
    if "qe" in s:
        qe, qq = agg(s["qe"]), agg(s["qq"])
        p.add("quartic", "norm", [f"residual against u_{a}^4 (beyond any ellipsoid)" for a in "xyz"],
              qe / np.sqrt(np.maximum(qq, 1e-12)), 1e-3)
    # aux
    for name in d.aux_bins:
        XX = np.einsum("cbkj,mb->mckj", s["aXX:" + name], mult)
        Xe = np.einsum("cbkj,mb->mckj", s["aXe:" + name], mult)
        cf = _solve6(XX, Xe)                     # (M, C, nb, 6)
        nbins = d.aux_edges[name].size - 1
        cf[:, :, nbins:, :] = np.nan
        # the trend across bins (per full span of the signal): what a linear dependence moves
        x = d.aux_centres[name]
        nb_w = XX[..., :nbins, 0]                          # (M, C, nbins) samples per bin
        y = cf[:, :, :nbins, :4]
        ok = np.isfinite(y).all(axis=-1) & (nb_w > 0)
        wgt = np.where(ok, nb_w, 0.0)
        xm = np.sum(wgt * x, axis=-1, keepdims=True) / np.maximum(wgt.sum(-1, keepdims=True), 1e-12)
        dx = (x - xm) * (wgt > 0)
        den = np.sum(wgt * dx * dx, axis=-1)
        slope = np.einsum("mcb,mcbj->mcj", wgt * dx, np.nan_to_num(y)) / np.maximum(den, 1e-12)[..., None]
        slope[(ok.sum(-1) < 3) | (den <= 0)] = np.nan
        for c in range(C):
            p.add("aux:" + name, ch[c], lab["aux"][name],
                  np.concatenate([cf[:, c].reshape(M, -1), slope[:, c]], axis=1), 1e-3)
    # frequency
    sp, spn = aggc(s["spec"]), aggc(s["spec_n"])
    av, avn = aggc(s["avar"]), aggc(s["avar_n"])
    blabs = [f"band {BAND_FRACTIONS[k]:.3g}-{BAND_FRACTIONS[k + 1]:.3g} x Nyquist"
             for k in range(BAND_FRACTIONS.size - 1)]
    alabs = [f"Allan variance at {tau} samples" for tau in TAUS]
    with np.errstate(divide="ignore", invalid="ignore"):
        for c in range(C):
            band = np.where((spn[:, c] > 0) & (sp[:, c] > 0), np.log(sp[:, c] / spn[:, c]), np.nan)
            allan = np.where((avn[:, c] > 0) & (av[:, c] > 0), np.log(av[:, c] / avn[:, c]), np.nan)
            p.add("frequency", ch[c], blabs, band, 0.01)
            p.add("frequency", ch[c], alabs, allan, 0.01)
    # weights (norm channel)
    nv, no = aggc(s["nvalid"])[:, 0], aggc(s["out"])[:, 0]
    fr = no / np.maximum(nv, 1)
    p.add("weights", "norm", "down-weighted, all", fr, _binom_floor(fr, nv))
    nvb, nob = s["nvalid"][0], s["out"][0]
    frb = np.where(nvb > 0, nob / np.maximum(nvb, 1), np.nan)
    vb = np.where((mult > 0) & (nvb > 0), frb[None, :], np.nan)
    fb = _binom_floor(np.broadcast_to(frb, vb.shape), np.broadcast_to(nvb, vb.shape))
    p.add("weights", "norm", lab["weights_block"], vb, fb, mult)
    co, cv = agg(s["cell_out"]), agg(s["cell_valid"])
    frc = np.where(cv >= 20, co / np.maximum(cv, 1), np.nan)
    p.add("weights", "norm", lab["weights_cell"], frc, _binom_floor(frc, cv))
    # raw
    rn = np.maximum(agg(s["raw_n"]), 1.0)                 # (M,)
    lc, lsn = np.einsum("jb,mb->mj", s["lat_c"], mult), np.einsum("jb,mb->mj", s["lat_s"], mult)
    pile = np.einsum("jsb,mb->mjs", s["pile"], mult)
    for j, ax in enumerate("xyz"):
        p.add("raw", "m" + ax, "lattice strength", np.hypot(lc[:, j], lsn[:, j]) / rn, 1.0 / np.sqrt(rn))
        for k, side in enumerate(("max", "min")):
            f = pile[:, j, k] / rn
            p.add("raw", "m" + ax, f"pile-up at {side}", f, _binom_floor(f, rn))
    # timing
    ck = np.einsum("kb,mb->mk", s["clock"], mult)
    nn = np.maximum(ck[:, 0], 1.0)
    ndt = np.maximum(ck[:, 0] + ck[:, 3] + ck[:, 4], 1.0)
    p.add("timing", "t", "mean |dt - dt0| / dt0", ck[:, 1] / nn, 1e-4)
    p.add("timing", "t", "rms (dt - dt0) / dt0", np.sqrt(ck[:, 2] / nn), 1e-4)
    p.add("timing", "t", "lost samples per step", ck[:, 3] / ndt, _binom_floor(ck[:, 3] / ndt, ndt))
    p.add("timing", "t", "steps shorter than dt0/2", ck[:, 4] / ndt, _binom_floor(ck[:, 4] / ndt, ndt))
    return p
