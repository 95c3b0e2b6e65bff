"""StreamingMKC: streaming equals batch at every checkpoint, no drift, fixed memory, exact restarts."""
import io
import tracemalloc

import numpy as np
import pytest

from mkc_stream.kernels import window as K
from mkc_stream.stream import StreamingMKC
from mkc_stream.verify import batch_checkpoint, capture


def linear_stream(seed, T=3000, n=4, m=2, outlier=0.15):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(T, m, n)) * [1.0, 3.0, 0.3, 1.0][:n]
    theta = rng.normal(size=n)
    Y = np.einsum("kmn,n->km", X, theta) + rng.normal(size=(T, m)) * (0.1 * np.arange(1, m + 1))
    bad = rng.random((T, m)) < outlier
    Y[bad] += rng.uniform(-20, 20, bad.sum())
    return X, Y, theta


@pytest.mark.parametrize("seed,W,Kk", [(0, 64, 8), (1, 128, 32), (2, 256, 16)])
def test_streaming_equals_batch_at_every_checkpoint(seed, W, Kk):
    X, Y, theta_true = linear_stream(seed, T=1500)
    est = StreamingMKC(4, 2, window=W, estep_every=Kk, d=[0.5, 0.5])
    checked = 0
    worst = 0.0
    for k in range(X.shape[0]):
        pre = capture(est)
        est.learn_one(X[k], Y[k])
        if est.esteps > pre["esteps"]:
            th_b, s_b, d_b = batch_checkpoint(est, pre)
            np.testing.assert_allclose(est.sigma, s_b, rtol=1e-12)
            np.testing.assert_allclose(est.d, d_b, rtol=1e-12)
            rel = np.linalg.norm(est.theta - th_b) / np.linalg.norm(th_b)
            worst = max(worst, rel)
            assert rel <= 1e-9, (k, rel)
            checked += 1
    assert checked >= (X.shape[0] - W) // Kk
    assert np.linalg.norm(est.theta - theta_true) < 0.05


def test_no_drift_between_checkpoints():
    X, Y, _ = linear_stream(5, T=2000)
    est = StreamingMKC(4, 2, window=200, estep_every=10**9, d=[0.5, 0.5])   # one E-step, then only add/remove
    est.learn_many(X, Y)
    st = est.views()
    count = est.window_count
    A = np.einsum("kmi,km,kmj->ij", st["X"][:count], st["C"][:count], st["X"][:count])
    b = np.einsum("kmi,km,km->i", st["X"][:count], st["C"][:count], st["Y"][:count])
    np.testing.assert_allclose(np.tril(st["A"]), np.tril(A), rtol=1e-10, atol=1e-10 * np.abs(A).max())
    np.testing.assert_allclose(st["theta"], np.linalg.solve(A, b), rtol=1e-9)


def test_save_restore_is_bit_exact(tmp_path):
    X, Y, _ = linear_stream(3, T=2500)
    a = StreamingMKC(4, 2, window=128, estep_every=16)
    a.learn_many(X[:1000], Y[:1000])
    path = tmp_path / "state.npz"
    a.save(path)
    a.learn_many(X[1000:], Y[1000:])
    b = StreamingMKC.load(path)
    b.learn_many(X[1000:], Y[1000:])
    for k, v in a.state.items():
        assert np.array_equal(v, b.state[k]), k
    # in-memory state round trip too
    c = StreamingMKC(4, 2, window=128, estep_every=16).load_state(a.state)
    assert np.array_equal(c.theta, a.theta)
    buf = io.BytesIO()
    a.save(buf)
    buf.seek(0)
    assert StreamingMKC.load(buf).snapshot().samples_seen == 2500


def test_nan_and_inf_are_rejected_and_counted():
    X, Y, _ = linear_stream(4, T=600)
    est = StreamingMKC(4, 2, window=128, estep_every=16)
    est.learn_many(X[:500], Y[:500])
    before = est.state
    x_bad = X[500].copy()
    x_bad[0, 1] = np.nan
    assert est.learn_one(x_bad, Y[500]) == K.REJECTED
    assert est.learn_one(X[500], [np.inf, 0.0]) == K.REJECTED
    after = est.state
    for k in before:
        if k != "cnt":
            assert np.array_equal(before[k], after[k], equal_nan=True), k
    assert est.snapshot().samples_rejected == 2 and est.snapshot().samples_seen == 500
    status = est.learn_many(np.where(np.arange(100)[:, None, None] % 10 == 0, np.nan, X[500:600]), Y[500:600])
    assert (status == K.REJECTED).sum() == 10
    assert np.isfinite(est.theta).all()


def test_memory_is_fixed():
    X, Y, _ = linear_stream(6, T=4000)
    est = StreamingMKC(4, 2, window=256, estep_every=32)
    ids = {k: id(v) for k, v in est.kernel_state.items()}
    nb = est.nbytes()
    est.learn_many(X[:1000], Y[:1000])
    tracemalloc.start()
    for _ in range(3):
        est.learn_many(X, Y)
    cur, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 64 * 1024          # only the per-call status array (T bytes) and small objects
    assert {k: id(v) for k, v in est.kernel_state.items()} == ids and est.nbytes() == nb


def test_warming_up_reset_snapshot_predict():
    X, Y, theta = linear_stream(7, T=400, outlier=0.0)
    est = StreamingMKC(4, 2, window=64, estep_every=8)
    assert est.learn_one(X[0], Y[0]) == K.WARMING_UP
    est.learn_many(X[1:], Y[1:])
    snap = est.snapshot()
    assert snap.status == "ok" and snap.window_count == 64 and snap.esteps > 0 and np.isfinite(snap.condition)
    np.testing.assert_allclose(est.predict_one(X[0]), X[0] @ theta, atol=0.3)
    assert est.weights().shape == (64, 2)
    est.reset()
    assert est.snapshot().samples_seen == 0 and not est.theta.any()
    with pytest.raises(ValueError):
        est.learn_one(np.zeros(3), [0.0, 0.0])
