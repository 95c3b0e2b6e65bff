"""Long runs (tools/long_run.py): fixed memory and no drift. Short by default, 10^7/10^8 with --runslow."""
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tools"))
import long_run as lr  # noqa: E402


def check_memory(samples):
    mem = lr.memory_run(samples, log=lambda s: None)
    assert mem["state_bytes_end"] == mem["state_bytes_start"]
    # learn_many allocates nothing per sample: only its (T,) int8 status array and small call overhead
    assert mem["learn_many_extra_bytes_max"] < lr.CHUNK + 10_000, mem
    assert mem["rss_growth_mb"] < 5.0, mem


def check_drift(samples):
    res = lr.drift_run(samples, log=lambda s: None)
    assert res["all_finite"]
    assert res["theta_rel_diff_vs_batch"] <= 1e-9, res
    assert res["sigma_rel_diff"] <= 1e-12 and res["d_rel_diff"] <= 1e-12, res
    assert res["accumulation_drift"] <= 1e-9, res
    assert res["restarts"] == 0, res


def test_memory_and_drift_short():
    check_memory(2_000_000)
    check_drift(1_000_000)


@pytest.mark.slow
def test_memory_fixed_over_1e7_samples():
    check_memory(10_000_000)


@pytest.mark.slow
def test_no_drift_after_1e8_samples():
    check_drift(100_000_000)
