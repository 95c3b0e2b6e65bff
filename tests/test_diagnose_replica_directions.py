"""The replicas' field directions: a 5-sample average of the fitted directions where the samples'
neighbours are close, the sample's own fitted direction where they are far apart
(:func:`mkc_stream.diagnose.model.far_neighbours`, the rule of ``noise_free_point``).

With unequal noise per axis the norm channel's noise depends on the direction; replicas run along
directions that are not the recording's (the average of samples 0.8 rad apart) get another noise
level, and the diagnosis reads the difference as a gap (figure-8 nulls of 10^6 samples at 50 Hz,
decimated by 50 in the fast profile, alarmed 4 times in 8)."""
import numpy as np
import pytest

from mkc_stream.diagnose.baseline import fit_baseline, robust_sd
from mkc_stream.diagnose.frame import prepare
from mkc_stream.diagnose.model import far_neighbours, noise_free_point
from mkc_stream.diagnose.replicas import norm_replicas
from mkc_stream.sim import SensorModel, generate, simulate
from mkc_stream.sim.trajectory import moving_average

RATE_HZ = 50.0
#: uT per axis: 4:1 between the axes, so that a wrong direction changes the norm channel's noise
#: by tens of percent (the 5-sample average gave replicas 26% quieter than this recording)
NOISE_UT = (0.2, 0.05, 0.05)


def _recording(n, seed):
    traj = generate("figure8", duration=n / RATE_HZ, rate=RATE_HZ, seed=seed, temp=None)
    return simulate(traj, SensorModel(noise=NOISE_UT), seed=seed + 1).recording


def _averaged_directions(v):
    u = moving_average(v, 5)
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def test_far_apart_samples_replicas_run_along_their_own_directions():
    # 10^5 samples at 50 Hz kept as 2000 (decimated by 50): ~0.8 rad of rotation between samples
    frame = prepare(_recording(100_000, 1700), 2000)
    assert frame.decimation == 50
    base = fit_baseline(frame)
    fit = base.fit
    far = far_neighbours(fit.m_corr, fit.state)
    assert far.mean() > 0.9
    np.testing.assert_array_equal(base.traj.field_dir[far], fit.v[far])
    np.testing.assert_array_equal(base.traj.field_dir[~far], _averaged_directions(fit.v)[~far])
    # the premise: the 5-sample average points far from the samples' own directions here
    cos = np.sum(_averaged_directions(fit.v) * fit.v, axis=1)
    assert np.median(np.arccos(np.clip(cos, -1.0, 1.0))) > 0.3           # rad

    # and the effect: the replicas' norm-channel noise (uT) is the recording's
    recorded = robust_sd(fit.e[fit.valid[:, 0], 0])
    r, _ = norm_replicas(frame, base, [], 8, 0)
    ratio = np.median([robust_sd(x) for x in r]) / recorded
    assert ratio == pytest.approx(1.0, abs=0.06)                         # the averaged directions: 0.74


def test_at_the_full_rate_no_sample_is_far_and_the_average_is_kept():
    frame = prepare(_recording(4000, 3), None)
    assert frame.decimation == 1
    base = fit_baseline(frame)
    fit = base.fit
    assert not far_neighbours(fit.m_corr, fit.state).any()
    np.testing.assert_array_equal(base.traj.field_dir, _averaged_directions(fit.v))


def test_far_neighbours_is_the_rule_noise_free_point_uses():
    frame = prepare(_recording(100_000, 1700), 2000)
    fit = fit_baseline(frame).fit
    # each sample three times: the middle copy's neighbours are its own copies (near), the outer
    # copies' neighbours lie ~0.8 rad apart (far)
    m, st = np.repeat(fit.m_corr, 3, axis=0), fit.state
    far = far_neighbours(m, st)
    assert 0.5 < far.mean() < 0.7
    assert not far[1::3].any()
    p = noise_free_point(m, st)
    # where far: the sample's own direction put on the fitted sphere, S (p - b) = F S (m - b) / |S (m - b)|
    xc = (m[far] - st.b) @ st.S.T
    np.testing.assert_allclose((p[far] - st.b) @ st.S.T, st.F * xc / np.linalg.norm(xc, axis=1)[:, None],
                               rtol=1e-9, atol=1e-9 * st.F)
    # elsewhere (interior samples): the direction of the neighbours' average
    near = np.flatnonzero(~far[1:-1]) + 1
    mh = 0.5 * (m[near - 1] + m[near + 1]) - st.b
    xh = mh @ st.S.T
    np.testing.assert_allclose((p[near] - st.b) @ st.S.T, st.F * xh / np.linalg.norm(xh, axis=1)[:, None],
                               rtol=1e-9, atol=1e-9 * st.F)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        far_neighbours(m[:, :2], st)
    assert not far_neighbours(m[:2], st).any()
