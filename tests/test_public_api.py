"""The public API: lazy top-level exports, the checkpoint listener, no private state used from outside."""
import json
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

import mkc_stream
import mkc_stream.calib
from mkc_stream.calib.streaming import MagCalibrator
from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.stream import StreamingMKC

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("module", [mkc_stream, mkc_stream.calib], ids=lambda m: m.__name__)
def test_every_exported_name_resolves(module):
    assert module.__all__ and len(set(module.__all__)) == len(module.__all__)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
        assert name in dir(module)
    with pytest.raises(AttributeError):
        getattr(module, "no_such_name")


def test_the_user_facing_names_are_there():
    from mkc_stream.calib.result import Calibration, Rejection
    from mkc_stream.diagnose import diagnose
    from mkc_stream.ingest.opener import open_source
    from mkc_stream.io.recording import read_recording, write_recording
    from mkc_stream.sim import simulate

    assert mkc_stream.StreamingMKC is StreamingMKC and mkc_stream.MagCalibrator is MagCalibrator
    assert mkc_stream.Calibration is Calibration and mkc_stream.calib.Calibration is Calibration
    assert mkc_stream.calib.Rejection is Rejection
    assert mkc_stream.read_recording is read_recording and mkc_stream.write_recording is write_recording
    assert mkc_stream.open_source is open_source and mkc_stream.simulate is simulate
    assert mkc_stream.diagnose.diagnose is diagnose          # mkc_stream.diagnose is the subpackage


def test_import_is_light():
    code = ("import sys, json, mkc_stream, mkc_stream.calib; "
            "print(json.dumps([m for m in ('numba', 'scipy', 'matplotlib') if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert json.loads(out.stdout) == []


@pytest.mark.parametrize("policy,chunk", [("fifo", 1), ("fifo", 100), ("direction", 1), ("direction", 3000)])
def test_the_listener_sees_every_checkpoint(policy, chunk):
    s = synthetic_mag(seed=4, N=3000, burst_fraction=0.1)
    calls = []
    cal = MagCalibrator(window=128, estep_every=16, policy=policy,
                        on_checkpoint=lambda c: calls.append((c.last_event, c.stream.esteps)))
    events = []
    for k in range(0, len(s.raw), chunk):
        events += cal.update(s.raw[k:k + chunk])
    assert len(events) > 100
    assert [ev for ev, _ in calls] == events == cal.history        # each one, once, in order
    # one checkpoint per E-step of the stream; the only other E-steps are those a checkpoint runs
    # itself (the restart on a new normalisation, a cold start it continues from): none with FIFO here
    inside = sum(after - ev.esteps for ev, after in calls)
    assert len(calls) + inside == cal.stream.esteps
    if policy == "fifo":
        assert inside == 0 and len(calls) == cal.stream.esteps


def test_listeners_are_called_in_order_and_can_be_removed():
    s = synthetic_mag(seed=3, N=1500, burst_fraction=0.0)
    order = []
    cal = MagCalibrator(window=128, estep_every=16, on_checkpoint=lambda c: order.append("first"))
    second = cal.add_listener(lambda c: order.append("second"))
    cal.update(s.raw[:1000])
    n = len(cal.history)
    assert n > 10 and order == ["first", "second"] * n
    cal.remove_listener(second)
    cal.update(s.raw[1000:])
    assert order[2 * n:] == ["first"] * (len(cal.history) - n)
    with pytest.raises(mkc_stream.MKCInputError):
        cal.add_listener(42)


def test_the_stream_properties_are_named_and_safe():
    rng = np.random.default_rng(0)
    est = StreamingMKC(3, 2, window=32, estep_every=4)
    est.learn_many(rng.normal(size=(100, 2, 3)), rng.normal(size=(100, 2)))
    snap = est.snapshot()
    assert (est.samples_seen, est.samples_rejected, est.window_count, est.esteps, est.status) == \
        (snap.samples_seen, snap.samples_rejected, snap.window_count, snap.esteps, snap.status)
    assert est.counters["esteps"] == est.esteps and est.counters["count"] == 32
    for name in ("sigma", "d", "a", "theta"):
        v = getattr(est, name)
        v[...] = -1.0                                      # a copy: the stream is not changed
        assert not np.array_equal(getattr(est, name), v)
    X = est.view("X")
    with pytest.raises(ValueError):
        X[0, 0, 0] = 1.0                                   # a read-only view
    assert X.shape == (32, 2, 3) and np.shares_memory(X, est.kernel_state["X"])


PRIVATE = re.compile(r"\._(st|args)\b")


def test_nothing_outside_stream_py_uses_the_private_state():
    offenders = []
    for folder in ("mkc_stream", "tests", "tools"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path == ROOT / "mkc_stream" / "stream.py" or path == pathlib.Path(__file__).resolve():
                continue
            for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if PRIVATE.search(line):
                    offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
