"""Streaming equals batch at every E-step checkpoint on real recordings.

The magnetometer calibrator is fed one sample at a time; whenever a sample triggers exactly one
regular checkpoint (one E-step, no restart, no cold start, no renormalisation in between), the
stream's (theta, sigma, d) must equal the batch kernels on the window it holds, from the warm start
it had (mkc_stream.verify.batch_checkpoint), to 1e-9 relative (in practice bit for bit).
"""
import pathlib

import numpy as np
import pytest

from mkc_stream.calib.streaming import MagCalibrator
from mkc_stream.io.recording import bundled_recording, load_broad, load_ck_explorer_csv, load_qmc5883l_csv
from mkc_stream.verify import batch_checkpoint, capture

DATA = pathlib.Path(__file__).parent / "data"

RECORDINGS = {
    "qmc5883l_noisy (bundled)": lambda: bundled_recording().mag[:6000],
    "qmc5883l_filtered": lambda: load_qmc5883l_csv(DATA / "qmc5883l-tomisuarez" / "filtered_raw_data.csv").mag[:6000],
    "ck_explorer": lambda: load_ck_explorer_csv(DATA / "ck-explorer-accmag" / "acc_mag_log.csv").mag,
    "broad_26_excerpt": lambda: load_broad(DATA / "broad" / "26_disturbed_phone_vibration_A_excerpt.mat").mag,
}


@pytest.mark.parametrize("name", sorted(RECORDINGS))
def test_streaming_equals_batch_at_every_checkpoint_on_real_data(name):
    mag = RECORDINGS[name]()
    cal = MagCalibrator(window=256, estep_every=32)
    est = cal.stream
    checked = 0
    worst = 0.0
    for k in range(mag.shape[0]):
        pre = capture(est)
        restarts = est.restarts
        normalisation = (cal.c0.copy(), cal.s0)
        cal.update(mag[k])
        regular = (est.esteps == pre["esteps"] + 1 and est.restarts == restarts
                   and np.array_equal(cal.c0, normalisation[0]) and cal.s0 == normalisation[1])
        if not regular:
            continue
        th_b, s_b, d_b = batch_checkpoint(est, pre)
        np.testing.assert_allclose(est.sigma, s_b, rtol=1e-12)
        np.testing.assert_allclose(est.d, d_b, rtol=1e-12)
        rel = np.linalg.norm(est.theta - th_b) / np.linalg.norm(th_b)
        worst = max(worst, rel)
        assert rel <= 1e-9, (name, k, rel)
        checked += 1
    assert checked >= min(100, (mag.shape[0] - 300) // 64), (name, checked)
    assert worst <= 1e-9
