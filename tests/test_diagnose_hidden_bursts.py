"""The hidden-burst scan: short runs of the norm residual, none of whose samples is an outlier, that
white noise would not give (a disturbance whose offset lies almost across the field). Flagged alike
in the recording and in every replica, counted among the bursts the replicas carry, and never a
step, a drift or a slow effect, which the diagnosis must find."""
from __future__ import annotations

import numpy as np
import pytest

from mkc_stream.diagnose.baseline import SCAN_CUT, estimate_bursts, hidden_bursts, scan_runs

N = 10_000


def _white(seed):
    return np.random.default_rng(seed).normal(size=N)


def test_white_noise_is_not_flagged():
    # the cut's union bound: at most 4 windows x 10^4 x 3.8e-8 = 1.5e-3 flagged windows per
    # recording; 30 recordings flag nothing at that rate (a 4.5% chance of one at the bound)
    ok = np.ones(N, dtype=bool)
    assert sum(int(hidden_bursts(_white(s), ok).any()) for s in range(30)) == 0


@pytest.mark.parametrize("start,length,size", [(5000, 30, -3.3), (200, 20, 2.5), (9000, 60, -2.0)])
def test_a_run_below_the_outlier_cut_is_flagged_where_it_is(start, length, size):
    z = _white(1)
    z[start:start + length] += size                  # every sample of the run stays within 4 sigma mostly
    flag = hidden_bursts(z, np.abs(z) < 4.0)
    idx = np.flatnonzero(flag)
    assert idx.size >= 0.6 * length
    assert idx.min() >= start - 4 and idx.max() < start + length + 4   # the burst, not the windows over it


def test_a_run_is_flagged_only_among_the_samples_given():
    z = _white(2)
    z[4000:4030] -= 3.3
    ok = np.ones(N, dtype=bool)
    ok[3990:4040] = False                            # already outliers (a burst's 4-sigma samples)
    assert not hidden_bursts(z, ok).any()


@pytest.mark.parametrize("name", ["step", "drift", "slow wave", "step in a drift"])
def test_steps_drifts_and_slow_effects_are_not_bursts(name):
    z = _white(3)
    t = np.arange(N)
    if name == "step":
        z[N // 2:] += 3.0                            # a hard-iron step of 3 sigma, kept
    elif name == "drift":
        z += 10.0 * t / N
    elif name == "slow wave":
        z += 3.0 * np.sin(2 * np.pi * t / 2000.0)    # a temperature cycle
    else:
        z += 8.0 * t / N + 2.5 * (t >= 3000)
    assert not hidden_bursts(z, np.ones(N, dtype=bool)).any()


def test_a_coloured_noise_is_measured_against_its_own_spread():
    # AR(1), phi 0.6, innovations of 1: the window sums spread 2x the white noise's; measured
    # against white noise they cross the cut all over, against their own spread rarely
    rng = np.random.default_rng(4)
    flagged = 0
    for _ in range(10):
        w = rng.normal(size=N)
        x = np.empty(N)
        x[0] = w[0]
        for k in range(1, N):
            x[k] = 0.6 * x[k - 1] + w[k]
        flagged += int(hidden_bursts(x, np.ones(N, dtype=bool)).sum())
    assert flagged <= 40


def test_two_bursts_in_one_region_are_both_flagged():
    z = _white(5)
    z[3000:3020] -= 3.0
    z[3030:3050] += 3.0
    flag = scan_runs(z, np.ones(N, dtype=bool))
    assert flag[3002:3018].all() and flag[3032:3048].all()
    assert not flag[3022:3028].any()


def test_the_scan_cut_is_a_rare_white_noise_excursion():
    from scipy.stats import norm

    assert 2 * norm.sf(SCAN_CUT) * 4 * N < 2e-3


def test_estimate_bursts_counts_a_hidden_burst_for_the_replicas():
    sigma = 0.3
    e = sigma * _white(6)
    e[6000:6030] -= 1.0                              # -1 uT for 30 samples, noise 0.3 uT
    b = estimate_bursts(e, np.ones(N, dtype=bool), sigma)
    assert b["count"] == 1
    assert 24 <= b["lengths"][0] <= 34
    assert b["sizes"][0] == pytest.approx(1.0, abs=0.25)
    assert estimate_bursts(sigma * _white(6), np.ones(N, dtype=bool), sigma)["count"] == 0


def test_block_stats_keep_a_hidden_burst_out_of_the_inlier_means():
    from types import SimpleNamespace

    from mkc_stream.diagnose import block_sums, panel

    rng = np.random.default_rng(7)
    v = rng.normal(size=(N, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    frame = SimpleNamespace(aux={}, t=np.arange(N) * 0.02, duration=N * 0.02, n_blocks=10,
                            block=np.repeat(np.arange(10), N // 10), dt0=0.02, unit="uT",
                            block_slices=lambda: [slice(k * 1000, (k + 1) * 1000) for k in range(10)])
    d = panel.make_design(frame, v, [1.0], {}, np.ones(3), np.zeros(3), np.ones(3))
    e = _white(8)[:, None]
    e[4300:4330, 0] -= 3.3
    s = block_sums.block_stats(d, e, np.ones((N, 1), dtype=bool), rng.normal(size=(N, 3)))
    assert s["out"][0, 4] >= 24                      # the burst is down-weighted ...
    mean = s["s1"][0] / s["n"][0]
    assert abs(mean[4]) < 4.0 / np.sqrt(1000)        # ... and its block's inlier mean is noise
