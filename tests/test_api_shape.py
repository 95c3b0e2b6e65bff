"""One default window and one verb set across the library, the C port's wrappers and the commands."""
from __future__ import annotations

import ctypes

import numpy as np
import pytest

from mkc_stream import cport as FW
from mkc_stream.calib.streaming import MagCalibrator
from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.defaults import DEFAULT_ESTEP_EVERY, DEFAULT_WINDOW
from mkc_stream.stream import StreamingMKC


def test_one_default_window_everywhere():
    import argparse

    from mkc_stream.commands.common import add_window_options

    p = argparse.ArgumentParser()
    add_window_options(p)
    args = p.parse_args([])
    assert (args.window, args.estep_every) == (DEFAULT_WINDOW, DEFAULT_ESTEP_EVERY)
    assert MagCalibrator().stream.config.window == DEFAULT_WINDOW
    assert StreamingMKC(3).config.window == DEFAULT_WINDOW
    assert MagCalibrator().stream.config.estep_every == DEFAULT_ESTEP_EVERY


@pytest.mark.skipif(FW.toolchain_problem() is not None, reason=f"C port not buildable here: {FW.toolchain_problem()}")
def test_the_c_port_defaults_to_the_same_window():
    from mkc_stream.cport import CMagCalibrator

    assert CMagCalibrator()._cfg.stream.window == DEFAULT_WINDOW
    # the C library's own default (mkc_config_default): min(capacity, DEFAULT_WINDOW); the host
    # build's capacity is 1024, so the same default
    lib = FW.load("double")
    cfg = type(CMagCalibrator()._cfg.stream)()
    lib.dll.mkc_config_default(ctypes.byref(cfg), 9, 1)
    assert cfg.window == DEFAULT_WINDOW


def test_learn_one_learn_many_and_the_old_name_agree():
    raw = synthetic_mag(seed=4, N=1500, burst_fraction=0.1).raw
    a, b, c = MagCalibrator(window=128), MagCalibrator(window=128), MagCalibrator(window=128)
    a.learn_many(raw)
    for m in raw:
        b.learn_one(m)
    c.update(raw)                    # the former name, kept for one release
    for other in (b, c):
        assert np.array_equal(a.accepted.hard_iron, other.accepted.hard_iron)
        assert [e.samples_seen for e in a.history] == [e.samples_seen for e in other.history]
