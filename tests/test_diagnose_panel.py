"""The panel's per-block sums and the coloured-noise fit's block offsets against plain loops.

The vectorised code (one pass of per-group sums per grouping, running sums for the Allan means, one
stacked solve) must give the sums a sample-by-sample loop gives.
"""
import numpy as np
import pytest

from mkc_stream.diagnose import block_sums, panel
from mkc_stream.diagnose.baseline import fit_baseline
from mkc_stream.diagnose.engine import Engine
from mkc_stream.diagnose.forms import _offsets, _variogram
from mkc_stream.diagnose.frame import prepare
from mkc_stream.sim import SensorModel, generate, simulate


@pytest.fixture(scope="module")
def engine():
    traj = generate("hand", duration=120, rate=20, seed=5, power=True)
    rec = simulate(traj, SensorModel(noise=0.1, burst_fraction=0.01), seed=6).recording
    frame = prepare(rec, 10_000)
    return Engine(frame, fit_baseline(frame), n_replicas=4)


@pytest.fixture(scope="module")
def sample(engine):
    d, n = engine.design, engine.frame.n
    rng = np.random.default_rng(3)
    e = rng.standard_t(4, size=(n, d.C)) * d.sigma[None, :]
    valid = rng.random((n, d.C)) > 0.05
    raw = engine.frame.m + rng.normal(0, 0.3, size=(n, 3))
    return d, e, valid, raw


def test_block_sums_match_a_loop_over_blocks(sample):
    d, e, valid, raw = sample
    s = block_sums.block_stats(d, e, valid, raw)
    z = e / d.sigma[None, :]
    far = valid & ~(np.abs(z) < 4.0)
    inl = valid & ~far & ~block_sums.between_outliers(far)   # a burst's interior is not an inlier
    tri = [(i, j) for i in range(6) for j in range(i, 6)]
    for b in range(d.n_blocks):
        blk = d.block == b
        for c in range(d.C):
            m = blk & inl[:, c]
            assert s["n"][c, b] == pytest.approx(m.sum())
            assert s["s1"][c, b] == pytest.approx(z[m, c].sum(), rel=1e-12, abs=1e-9)
            assert s["s2"][c, b] == pytest.approx(np.sum(z[m, c] ** 2), rel=1e-12)
            assert s["nvalid"][c, b] == (blk & valid[:, c]).sum()
            assert s["out"][c, b] == (blk & valid[:, c] & ~inl[:, c]).sum()
            XX = d.P[m].T @ d.P[m]
            np.testing.assert_allclose(s["tXX"][c, b], [XX[i, j] for i, j in tri], rtol=1e-12, atol=1e-9)
            np.testing.assert_allclose(s["tXe"][c, b], d.P[m].T @ z[m, c], rtol=1e-12, atol=1e-9)
            for k in range(d.n_cells):
                mk = m & (d.cell == k)
                assert s["cell_n"][c, b, k] == mk.sum()
                assert s["cell_s"][c, b, k] == pytest.approx(z[mk, c].sum(), rel=1e-12, abs=1e-9)
        for k in range(d.n_cells):
            mk = blk & (d.cell == k) & valid[:, 0]
            assert s["cell_valid"][b, k] == mk.sum()
            assert s["cell_out"][b, k] == (mk & ~inl[:, 0]).sum()
        ph = 2 * np.pi * (raw[blk] - d.lattice_phase) / d.lattice_q
        np.testing.assert_allclose(s["lat_c"][:, b], np.cos(ph).sum(axis=0), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(s["lat_s"][:, b], np.sin(ph).sum(axis=0), rtol=1e-12, atol=1e-9)
        hi = raw >= raw.max(axis=0) - d.pile_tol
        lo = raw <= raw.min(axis=0) + d.pile_tol
        np.testing.assert_array_equal(s["pile"][:, 0, b], hi[blk].sum(axis=0))
        np.testing.assert_array_equal(s["pile"][:, 1, b], lo[blk].sum(axis=0))
    for name, bins in d.aux_bins.items():
        for b in range(d.n_blocks):
            for k in range(panel.N_AUX_BINS):
                m = (d.block == b) & (bins == k) & inl[:, 1]
                np.testing.assert_allclose(s["aXe:" + name][1, b, k], d.P[m].T @ z[m, 1], rtol=1e-12, atol=1e-9)
    assert s["rXX"].shape == (d.n_blocks, 6) and s["qq"].shape == (d.n_blocks, 3)


def test_allan_variance_sums_match_the_definition(sample):
    d, e, valid, raw = sample
    s = block_sums.block_stats(d, e, valid, raw)
    z = e / d.sigma[None, :]
    far = valid & ~(np.abs(z) < 4.0)
    inl = valid & ~far & ~block_sums.between_outliers(far)   # a burst's interior is not an inlier
    zi = np.where(inl, z, 0.0)
    lens = np.array([sl.stop - sl.start for sl in d.slices])
    L = int(lens.min())
    for b, sl in enumerate(d.slices):
        x = zi[sl.start: sl.start + L, 0]
        m = inl[sl.start: sl.start + L, 0]
        x = np.where(m, x - x.sum() / max(m.sum(), 1), 0.0)
        for i, tau in enumerate(panel.TAUS):
            k = L // tau
            if k < 4:                              # too few means: the statistic is left out
                assert s["avar_n"][0, b, i] == 0
                continue
            means = np.array([x[j * tau:(j + 1) * tau].mean() for j in range(k)])
            assert s["avar"][0, b, i] == pytest.approx(0.5 * np.sum(np.diff(means) ** 2), rel=1e-10)
            assert s["avar_n"][0, b, i] == k - 1


def test_block_offsets_and_their_variogram_match_plain_loops(engine):
    env, frame = engine.env, engine.frame
    rng = np.random.default_rng(8)
    e = rng.normal(size=frame.n)
    mask = rng.random(frame.n) > 0.1
    mask[frame.block == 2] = False                 # a block with too few samples is left out
    o = _offsets(env, e, mask)
    v = engine.base.fit.v
    P = np.column_stack([np.ones(frame.n), v, v[:, 0] ** 2 - 1 / 3, v[:, 1] ** 2 - 1 / 3])
    Sinv = np.linalg.inv(engine.base.fit.state.S)
    for b in range(frame.n_blocks):
        m = (frame.block == b) & mask
        if b == 2:
            assert np.isnan(o[b]).all()
            continue
        X = P[m]
        coef = np.linalg.solve(X.T @ X + 1e-3 * m.sum() * np.eye(6), X.T @ e[m])
        np.testing.assert_allclose(o[b], Sinv @ coef[1:4], rtol=1e-10, atol=1e-12)
    mult = np.ones(frame.n_blocks)
    mult[5] = 0
    g = _variogram(o, mult, 8)
    for k in range(1, 9):
        d2 = [np.sum((o[b + k] - o[b]) ** 2) for b in range(frame.n_blocks - k)
              if mult[b] > 0 and mult[b + k] > 0 and np.isfinite(o[b]).all() and np.isfinite(o[b + k]).all()]
        assert g[k - 1] == pytest.approx(np.mean(d2), rel=1e-12)


def test_group_sums_add_each_group_in_sample_order():
    """The one-pass group sums are the additions np.bincount makes (sample order, from 0.0), to
    the last bit; -1 is no group."""
    from mkc_stream.diagnose.panel_sums import group_sums, regression_sums

    rng = np.random.default_rng(11)
    n, G = 3000, 7
    groups = np.stack([rng.integers(-1, G, n), rng.integers(-1, 3, n)], axis=1).astype(np.int64)
    X = rng.standard_t(3, size=(n, 4))
    out = group_sums(groups, G, X)
    for q in range(2):
        ok = groups[:, q] >= 0
        for j in range(4):
            np.testing.assert_array_equal(out[q, :, j], np.bincount(groups[ok, q], X[ok, j], minlength=G))
    PP, P = rng.normal(size=(n, 21)), rng.normal(size=(n, 6))
    fi, zi = (rng.random((n, 2)) > 0.2).astype(float), rng.normal(size=(n, 2))
    R = regression_sums(groups, G, PP, P, fi, zi)
    for q in range(2):
        ok = groups[:, q] >= 0
        for c in range(2):
            for j in range(21):
                np.testing.assert_array_equal(R[q, :, c, j], np.bincount(groups[ok, q], PP[ok, j] * fi[ok, c],
                                                                         minlength=G))
            for j in range(6):
                np.testing.assert_array_equal(R[q, :, c, 21 + j], np.bincount(groups[ok, q], P[ok, j] * zi[ok, c],
                                                                              minlength=G))


def test_a_panel_for_several_weightings_is_each_weighting_s_panel(sample):
    """Panel rows for M block weightings at once equal the panels of each weighting alone:
    values, weights (a per-block weight), floors, families and labels."""
    d, e, valid, raw = sample
    s = block_sums.block_stats(d, e, valid, raw)
    rng = np.random.default_rng(4)
    mults = rng.integers(0, 3, size=(3, d.n_blocks)).astype(float)
    p = panel.evaluate(d, s, mults)
    v, w, f = p.matrices()
    np.testing.assert_array_equal(p.values(), v)
    assert v.shape == w.shape == f.shape == (3, len(p.labels)) and len(p.family) == len(p.labels)
    for m in range(3):
        one = panel.evaluate(d, s, mults[m])
        x1, w1, f1 = one.arrays()
        np.testing.assert_allclose(v[m], x1, rtol=1e-12, atol=1e-12, equal_nan=True)
        np.testing.assert_allclose(w[m], w1, rtol=1e-12, atol=1e-12, equal_nan=True)
        np.testing.assert_allclose(f[m], f1, rtol=1e-12, atol=1e-12, equal_nan=True)
        assert one.labels == p.labels and one.family == p.family
    # a block left out by a weighting weighs 0 in the time family, whose weights are per block
    time = np.array([fam == "time" for fam in p.family])
    np.testing.assert_array_equal(w[:, time], np.tile(np.repeat(mults, 6, axis=1), (1, d.C)))


def test_the_bootstrap_reads_the_statistics_the_gap_index_reads(engine):
    """A bootstrap resample that keeps every block once gives the point gap index: every
    statistic is a function of the block sums (decision 0028). The panel once held the E-step's
    (sigma, d), which the bootstraps left out; the selection then compared point gaps that read
    it with bootstrap gains that did not."""
    from mkc_stream.diagnose.engine import Candidate

    ev = engine.evaluate(Candidate())
    engine.calibrate(ev)                 # the index's normalisation, as diagnose sets it
    p = panel.evaluate(engine.design, ev.real_bs, engine.all_mult)
    assert "kernel" not in set(p.family)
    ones = np.ones((2, engine.frame.n_blocks))
    np.testing.assert_allclose(engine.boot_gaps(ev, ones), ev.G, rtol=1e-9)


def test_replicas_share_their_recorded_sums_and_score_as_if_recomputed(engine):
    """A replica's raw-value and clock sums are computed once per set of replicas and shared by
    every candidate scored on it; scoring with them equals scoring from scratch."""
    from mkc_stream.diagnose.engine import Candidate

    ev = engine.evaluate(Candidate())
    again = engine.evaluate(Candidate())                  # another candidate object, the same replicas
    for bs, bs2 in zip(ev.rep_bs, again.rep_bs):
        assert bs["lat_c"] is bs2["lat_c"]                  # the same cached sums
    fresh = Engine(engine.frame, engine.base, n_replicas=4)
    ev2 = fresh.evaluate(Candidate())
    np.testing.assert_array_equal(ev.rep_values, ev2.rep_values)
    from mkc_stream.diagnose.baseline import estimate_bursts

    bursts = estimate_bursts(ev.e[:, 0], ev.valid[:, 0], engine.base.sigma[0])     # as evaluate() has it
    r_norm, raw = engine._norm(Candidate(), engine.R, bursts)
    clocks = engine._clock(Candidate(), engine.R) if engine.frame.timestamps_real else [None] * engine.R
    for k, bs in enumerate(ev.rep_bs):
        want = block_sums.recorded_stats(engine.design, raw[k], clocks[k])
        for key in ("lat_c", "lat_s", "pile", "raw_n", "clock"):
            np.testing.assert_array_equal(bs[key], want[key])


def test_bootstrap_noise_fits_equal_fits_without_the_per_block_cache(engine):
    """The coloured-noise estimator keeps per-block pieces across block weightings (the
    bootstrap's 40 resamples); an estimate after other weightings equals one from a fresh cache."""
    from mkc_stream.diagnose.engine import Candidate
    from mkc_stream.diagnose.forms import Env
    from mkc_stream.sim.effects import noise_fit

    ev = engine.evaluate(Candidate())
    rng = np.random.default_rng(2)
    mults = [rng.integers(0, 3, size=engine.frame.n_blocks).astype(float) for _ in range(3)]
    warm = Env(engine.frame, engine.base)
    for m in mults[:2]:
        noise_fit._within_block_excess(warm, noise_fit._noise_samples(warm, ev), m)
        noise_fit._block_mean_share_norm(warm, m, 2.0)
    cold = Env(engine.frame, engine.base)
    a = noise_fit._within_block_excess(warm, noise_fit._noise_samples(warm, ev), mults[2])
    b = noise_fit._within_block_excess(cold, noise_fit._noise_samples(cold, ev), mults[2])
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    # against the autocovariance summed over the weighting's blocks directly
    slices = [sl for sl, w in zip(engine.frame.block_slices(), mults[2]) if w > 0]
    real, reps = noise_fit._noise_samples(cold, ev)
    K, sig = a[0].size - 1, engine.base.sigma[0]
    s, c = noise_fit._acov(real.e / sig, real.ok, slices, K)
    rep = np.array([(lambda sc: sc[0] / np.maximum(sc[1], 1))(noise_fit._acov(r.e / sig, r.ok, slices, K))
                    for r in reps])
    np.testing.assert_array_equal(a[1], s / np.maximum(c, 1) - rep.mean(axis=0))
    assert noise_fit._block_mean_share_norm(warm, mults[2], 2.0) == noise_fit._block_mean_share_norm(cold, mults[2],
                                                                                                       2.0)
    keep = [b for b, w in enumerate(mults[2]) if w > 0]
    assert len(keep) < engine.frame.n_blocks       # a resample leaves blocks out
