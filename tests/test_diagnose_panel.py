"""The panel's per-block sums and the coloured-noise fit's block offsets against plain loops.

The vectorised code (one sparse product per grouping, running sums for the Allan means, one
stacked solve) must give the sums a sample-by-sample loop gives.
"""
import numpy as np
import pytest

from mkc_stream.diagnose import panel
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
    s = panel.block_stats(d, e, valid, raw)
    z = e / d.sigma[None, :]
    far = valid & ~(np.abs(z) < 4.0)
    inl = valid & ~far & ~panel.between_outliers(far)   # a burst's interior is not an inlier
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
    s = panel.block_stats(d, e, valid, raw)
    z = e / d.sigma[None, :]
    far = valid & ~(np.abs(z) < 4.0)
    inl = valid & ~far & ~panel.between_outliers(far)   # a burst's interior is not an inlier
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
