"""The streamed calibration is a well-conditioned function of its input (the E-step's weak prior on
sigma, kernels/estep.py), and the prior does not hide bursts (sigma restarts when one enters).

Without the prior a 1e-7 relative change of a real recording moved its streamed calibration by up
to 2.8e-3: on clean windows the likelihood is flat in sigma and the capped E-step stopped anywhere
along the ridge. That is also what kept the C float build from following the reference."""
import json
import pathlib
import sys

import numpy as np
import pytest

from mkc_stream import cport as FW
from mkc_stream.stream import StreamingMKC

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import golden as GV  # noqa: E402  (tools/golden.py: the vectors' files)

INDEX = json.loads((GV.GOLDEN_DIR / "index.json").read_text())


def _vector(name):
    v = next(v for v in INDEX["vectors"] if v["name"] == name)
    return GV.stored_input(v), v["config"]


def _worst_accepted_difference(a, b):
    worst = 0.0
    for p, q in zip(a, b):
        assert p["accepted"] == q["accepted"]
        if p["accepted"] and p["has_trial"]:
            F = p["field"]
            worst = max(worst, FW.rel_diff(q["theta"], p["theta"]), np.abs(q["hard_iron"] - p["hard_iron"]).max() / F,
                        FW.rel_diff(q["soft_iron"].ravel(), p["soft_iron"].ravel()), abs(q["field"] - F) / F)
    return worst


@pytest.mark.parametrize("pull,bound", [(None, 1e-5), (0.0, None)])
def test_streamed_calibration_under_a_1e7_input_change(pull, bound):
    """QMC5883L filtered (22,745 samples, 503 accepted checkpoints): input times (1 + 1e-7 N(0,1)) from
    sample 1000 on, after the final feature normalisation (checkpoint 20, sample 658). Before it, the
    calibrator waits while its window's sphere fit is a cloud (spread > 30% of the radius), and the
    sphere fit of a cloud is ill-conditioned by nature: a 1e-7 change moves that spread by up to 3
    points, and on this recording it sits at 30.0% at checkpoint 20, so a perturbed stream can
    normalise one checkpoint later and follow another path (finals up to 10.4 counts apart per axis, 1.8 of the
    reported standard deviations; docs/decisions/0016). This test is about the E-step afterwards."""
    inp, cfg = _vector("qmc5883l_filtered")
    kw = {} if pull is None else {"sigma_pull": pull}
    m = inp["mags"]
    m2 = m.copy()
    m2[1000:] *= 1.0 + 1e-7 * np.random.default_rng(0).standard_normal(m[1000:].shape)
    a, _ = FW.python_checkpoints(m, cfg["window"], cfg["estep_every"], inp["unit"], policy=cfg["policy"], **kw)
    b, _ = FW.python_checkpoints(m2, cfg["window"], cfg["estep_every"], inp["unit"], policy=cfg["policy"], **kw)
    worst = _worst_accepted_difference(a, b)
    if bound is not None:
        assert worst <= bound               # measured 3.3e-7
    else:
        assert worst > 1e-4                 # the paper's pure ML on the same stream: the ridge is real (2.8e-3)


def test_a_burst_after_a_clean_stretch_is_down_weighted():
    """Clean samples pull sigma to sigma_hi, where the likelihood's slope is weaker than the prior's:
    when a burst enters, sigma must restart from the Gaussian regime and find the robust optimum."""
    rng = np.random.default_rng(3)
    n, T = 4, 4000
    theta = np.array([1.0, -2.0, 0.5, 3.0])
    X = rng.normal(size=(T, n))
    Y = X @ theta + 0.1 * rng.normal(size=T)
    burst = np.zeros(T, bool)
    burst[2600:2700] = True                     # 100 of the window's 256 samples, 5-10 sigma of noise off
    Y[burst] += rng.uniform(0.5, 1.0, burst.sum())
    est = StreamingMKC(n, 1, window=256, estep_every=32)
    est.learn_many(X[:2600], Y[:2600])
    assert est.snapshot().sigma[0] == pytest.approx(est.config.sigma_hi)
    est.learn_many(X[2600:2720], Y[2600:2720])
    s = est.snapshot()
    assert s.sigma[0] < 5.0
    assert np.abs(s.theta - theta).max() < 0.02        # least squares on this window: ~0.1 off
    X_w, Y_w, _ = est.window()
    ls = np.linalg.lstsq(X_w[:, 0, :], Y_w[:, 0], rcond=None)[0]
    assert np.abs(ls - theta).max() > 3 * np.abs(s.theta - theta).max()


@pytest.mark.parametrize("pull", [-0.05, float("nan"), float("inf")])
def test_a_bad_sigma_pull_is_refused(pull):
    with pytest.raises(ValueError, match="sigma_pull"):
        StreamingMKC(4, 1, sigma_pull=pull)
