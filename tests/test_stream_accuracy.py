"""The streaming calibrator's accuracy targets on synthetic burst streams (tools/study_stream.py is the full study).

Default run: 5 seeds per burst level; `--runslow`: the 20 seeds of the study. Thresholds are the
issue's: hard-iron error median <= 0.05 uT at 10 % bursts, <= 0.2 uT at 25 %, none above 1 uT,
every stream accepted; the same streams defeat least squares by two orders of magnitude.
"""
import pathlib
import sys

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tools"))
import study_stream as ss  # noqa: E402


def run(seeds, frac):
    rows = ss.synthetic_study(seeds, [frac], 3000, 512, 32, {}, log=lambda s: None)
    assert all(r["stream"]["accepted"] for r in rows), [r["stream"] for r in rows if not r["stream"]["accepted"]]
    b = np.array([r["stream"]["hard_iron_err"] for r in rows])
    ls = np.array([r["ls"]["hard_iron_err"] for r in rows])
    heading = np.array([r["stream"]["heading_err_deg"] for r in rows])
    return b, ls, heading


LIMITS = {0.1: 0.05, 0.25: 0.2}


@pytest.mark.parametrize("frac", [0.1, 0.25])
def test_streaming_hard_iron_accuracy_under_bursts(frac):
    b, ls, heading = run(5, frac)
    assert np.median(b) <= LIMITS[frac], b
    assert b.max() <= 1.0, b
    assert np.median(ls) > 20 * np.median(b)          # the bursts really are there
    assert heading.max() < 1.0, heading


@pytest.mark.slow
@pytest.mark.parametrize("frac", [0.0, 0.1, 0.25])
def test_streaming_hard_iron_accuracy_20_seeds(frac):
    b, ls, heading = run(20, frac)
    assert np.median(b) <= LIMITS.get(frac, 0.05), b
    assert b.max() <= 1.0, b


def test_heading_error_metric():
    S = np.eye(3)
    b = np.array([1.0, 2.0, 3.0])
    assert ss.heading_error_deg(b, S, b, S) < 1e-9
    # a 1 uT hard-iron error along x in a 25 uT horizontal field: about asin(1/25) = 2.3 deg
    e = ss.heading_error_deg(b + [1.0, 0, 0], S, b, S)
    assert 2.0 < e < 2.6
