"""Hostile use of the public streaming API and the calibration core.

Each probe asserts the documented outcome: a ValueError (or TypeError for a wrong type) with a
message that names the problem, and nothing changed; never an abort, a segfault or a silent run.
"""
import io
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mkc_stream._validation import MKCInputError
from mkc_stream.batch import MKCRegressor
from mkc_stream.calib.acceptance import AcceptanceRules
from mkc_stream.calib.ellipsoid import EllipsoidError, gross_outlier_mask
from mkc_stream.calib.fit import fit_ellipsoid
from mkc_stream.calib.streaming import MagCalibrator
from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.kernels import BAD_INPUT
from mkc_stream.kernels import window as K
from mkc_stream.state import MAX_WINDOW, VALID_STATUS
from mkc_stream.stream import StreamingMKC

THETA = np.array([1.0, -2.0, 0.5])
W = 32


def linear(seed, T, n=3):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(T, 1, n))
    Y = X[:, 0, :] @ THETA[:n] + 0.05 * rng.normal(size=T)
    return X, Y[:, None]


def trained(T=100, window=W, estep_every=8):
    est = StreamingMKC(3, 1, window=window, estep_every=estep_every)
    X, Y = linear(0, T)
    est.learn_many(X, Y)
    return est


def same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)


# -- item 1: learn_one's slot ---------------------------------------------------------------

@pytest.mark.parametrize("fed, slot", [(0, 64), (0, 10**6), (0, 1), (0, 63), (5, 6), (5, 31 + 1), (40, W),
                                       (40, 10**6), (5, -2), (5, -10**6)])
def test_slot_outside_the_window_is_refused_and_changes_nothing(fed, slot):
    est = StreamingMKC(3, 1, window=64 if fed == 0 else W)
    X, Y = linear(1, fed + 1)
    if fed:
        est.learn_many(X[:fed], Y[:fed])
    before = est.state
    with pytest.raises(ValueError, match=rf"slot {slot} is outside the window"):
        est.learn_one(X[fed], Y[fed], slot=slot)
    assert same_state(before, est.state)


def test_slot_must_be_an_integer():
    est = StreamingMKC(3, 1, window=W)
    with pytest.raises(TypeError, match="slot must be an integer"):
        est.learn_one(np.ones((1, 3)), np.ones(1), slot=1.5)


def test_explicit_slots_give_the_same_state_as_the_ring_buffer():
    """slot == count fills the next slot and slot < count replaces one: the ring buffer's own
    order written out by hand reproduces its state bit for bit."""
    X, Y = linear(2, 3 * W)
    ring, manual = StreamingMKC(3, 1, window=W), StreamingMKC(3, 1, window=W)
    for t in range(3 * W):
        ring.learn_one(X[t], Y[t])
        manual.learn_one(X[t], Y[t], slot=t % W)
    assert same_state(ring.state, manual.state)       # (3W samples: the ring's head is back at 0)


def test_the_kernel_refuses_a_bad_slot_or_head_itself():
    """The jitted kernel checks too (as the C port): a caller going round the class gets
    BAD_INPUT, and nothing is written."""
    est = trained(T=10)
    before = est.state
    x, y = np.ones((1, 3)), np.ones(1)
    assert K.learn_one(*est.kernel_args, x, y, W) == BAD_INPUT
    assert K.learn_one(*est.kernel_args, x, y, 11) == BAD_INPUT        # past the 10 filled slots
    head = est.counters["head"]
    est.kernel_state["cnt"][K.C_HEAD] = 10**6                          # (a write: through the kernel's arrays)
    assert K.learn_one(*est.kernel_args, x, y, -1) == BAD_INPUT
    est.kernel_state["cnt"][K.C_HEAD] = head
    assert same_state(before, est.state)


@settings(max_examples=60, deadline=None)
@given(fed=st.integers(0, 2 * W), slot=st.integers(-3, 2 * W + 2))
def test_any_slot_is_used_or_refused(fed, slot):
    est = StreamingMKC(3, 1, window=W)
    X, Y = linear(3, fed + 1)
    if fed:
        est.learn_many(X[:fed], Y[:fed])
    count = est.window_count
    seen = est.samples_seen
    before = est.state
    if slot == -1 or 0 <= slot <= min(count, W - 1):
        status = est.learn_one(X[fed], Y[fed], slot=slot)
        assert status in VALID_STATUS
        assert est.samples_seen == seen + 1
        assert est.window_count == count + (slot == count or (slot == -1 and count < W))
    else:
        with pytest.raises(ValueError, match="outside the window"):
            est.learn_one(X[fed], Y[fed], slot=slot)
        assert same_state(before, est.state)


def test_learn_many_refuses_a_shape_that_does_not_divide():
    est = StreamingMKC(3, 2, window=W)
    with pytest.raises(ValueError, match=r"expected X \(T, 2, 3\)"):
        est.learn_many(np.ones((5, 4)), np.ones((5, 2)))


# -- item 2: load_state / load -------------------------------------------------------------

CORRUPTIONS = [
    # (field, flat index, value, message part)
    ("cnt", K.C_HEAD, 10**6, "ring-buffer head"),
    ("cnt", K.C_HEAD, -3, "ring-buffer head"),
    ("cnt", K.C_COUNT, 10**6, "window count"),
    ("cnt", K.C_COUNT, -1, "window count"),
    ("cnt", K.C_SEEN, -5, "samples seen"),
    ("cnt", K.C_ESTEPS, -1, "E-steps"),
    ("cnt", K.C_STATUS, 99, "status 99"),
    ("cnt", K.C_LAST_SLOT, 10**7, "last slot"),
    ("cnt", K.C_FACTOR_AGE, -7, "factor age"),
    ("icfg", K.I_N, 100, "n 100 in the state, 3 here"),
    ("icfg", K.I_W, 10**6, "window 1000000 in the state"),
    ("icfg", K.I_K, 4, "estep_every 4 in the state, 8 here"),
    ("icfg", K.I_M, 5, "m 5 in the state"),
    ("fcfg", K.F_SIG_LO, np.nan, "sigma_lo nan in the state"),
    ("fcfg", K.F_AFAC, 2.0, "a_factor 2.0 in the state, 1.5 here"),
    ("sigma", 0, np.nan, "'sigma' has NaN/inf"),
    ("sigma", 0, -1.0, "sigma has values <= 0"),
    ("d", 0, 0.0, "d has values"),
    ("d", 0, np.nan, "d has values"),
    ("theta", 1, np.inf, "'theta' has NaN/inf"),
    ("X", 5, np.nan, "'X' has NaN/inf"),
    ("Y", 3, -np.inf, "'Y' has NaN/inf"),
    ("C", 2, -1.0, "'C' has negative"),
]


@pytest.mark.parametrize("field, index, value, message", CORRUPTIONS)
def test_corrupt_state_is_refused_and_nothing_changes(field, index, value, message):
    src = trained()
    target = StreamingMKC(3, 1, window=W, estep_every=8)
    X, Y = linear(4, 20)
    target.learn_many(X, Y)
    before = target.state
    bad = src.state
    bad[field].flat[index] = value
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        target.load_state(bad)
    assert same_state(before, target.state)


def test_state_of_another_configuration_names_the_fields():
    """A period-8 state loaded into estep_every=4 used to load silently and run with period 8."""
    src = trained(estep_every=8)
    target = StreamingMKC(3, 1, window=W, estep_every=4)
    before = target.state
    with pytest.raises(ValueError, match="another configuration: estep_every 8 in the state, 4 here"):
        target.load_state(src.state)
    assert same_state(before, target.state)
    with pytest.raises(ValueError, match="field 'X' has shape/dtype"):
        StreamingMKC(3, 1, window=2 * W, estep_every=8).load_state(src.state)


@pytest.mark.parametrize("change, message", [
    (lambda s: s.pop("theta"), r"missing \['theta'\]"),
    (lambda s: s.update(extra=np.zeros(1)), r"unexpected \['extra'\]"),
    (lambda s: s.update(cnt=s["cnt"].astype(np.int32)), "field 'cnt' has shape/dtype"),
    (lambda s: s.update(theta=s["theta"][:2]), "field 'theta' has shape/dtype"),
])
def test_state_with_missing_extra_or_mistyped_fields_is_refused(change, message):
    target = StreamingMKC(3, 1, window=W, estep_every=8)
    before = target.state
    bad = trained().state
    change(bad)
    with pytest.raises(ValueError, match=message):
        target.load_state(bad)
    assert same_state(before, target.state)
    with pytest.raises(ValueError, match="dict of arrays"):
        target.load_state([1, 2, 3])


def test_a_valid_state_still_loads_bit_exactly():
    src = trained()
    dst = StreamingMKC(3, 1, window=W, estep_every=8).load_state(src.state)
    X, Y = linear(5, 50)
    assert np.array_equal(src.learn_many(X, Y), dst.learn_many(X, Y))
    assert same_state(src.state, dst.state)


FIELD_VALUES = {
    "int64": st.one_of(st.integers(-3, 3 * W), st.sampled_from([-2**63, 2**63 - 1, -1, 10**6])),
    "float64": st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-10, 10)),
}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_random_corruption_is_refused_atomically_or_loads_a_runnable_state(data):
    src = trained()
    bad = src.state
    for _ in range(data.draw(st.integers(1, 3), label="fields")):
        field = data.draw(st.sampled_from(sorted(bad)), label="field")
        index = data.draw(st.integers(0, bad[field].size - 1), label="index")
        bad[field].flat[index] = data.draw(FIELD_VALUES[str(bad[field].dtype)], label="value")
    target = StreamingMKC(3, 1, window=W, estep_every=8)
    X, Y = linear(6, 40)
    target.learn_many(X[:10], Y[:10])
    before = target.state
    try:
        target.load_state(bad)
    except ValueError:
        assert same_state(before, target.state)
        return
    status = target.learn_many(X, Y)            # a state that passed runs: no crash, valid statuses
    assert set(status.tolist()) <= VALID_STATUS
    snap = target.snapshot()
    assert 0 <= snap.window_count <= W


def test_save_load_round_trip_and_damaged_files(tmp_path):
    src = trained()
    path = tmp_path / "state.npz"
    src.save(path)
    assert same_state(StreamingMKC.load(path).state, src.state)
    data = path.read_bytes()
    for damaged in (data[: len(data) // 2], data[:100], b"", b"not a state file at all", data[:-30]):
        with pytest.raises(ValueError, match="stream state file"):
            StreamingMKC.load(io.BytesIO(damaged))
    buf = io.BytesIO()
    np.save(buf, np.zeros(3))
    with pytest.raises(ValueError, match="single array"):
        StreamingMKC.load(io.BytesIO(buf.getvalue()))
    with pytest.raises(FileNotFoundError):
        StreamingMKC.load(tmp_path / "missing.npz")


def _rewrite_meta(src, edit):
    buf = io.BytesIO()
    src.save(buf)
    with np.load(io.BytesIO(buf.getvalue())) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays.pop("__meta__")).decode())
    edit(meta)
    out = io.BytesIO()
    np.savez(out, __meta__=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
    return io.BytesIO(out.getvalue())


@pytest.mark.parametrize("edit, message", [
    (lambda m: m.update(version=1), "version 1"),
    (lambda m: m["config"].update(estep_every=4), "estep_every 8 in the state, 4 here"),
    (lambda m: m["config"].update(window=10**7), "largest supported"),
    (lambda m: m["config"].update(bogus=1), "bogus"),
    (lambda m: m.pop("config"), "KeyError"),
    (lambda m: m.update(sigma0=[float("nan")]), "sigma must be finite"),
])
def test_state_file_with_a_bad_header_is_refused(edit, message):
    with pytest.raises(ValueError, match=message):
        StreamingMKC.load(_rewrite_meta(trained(), edit))


@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_truncated_or_flipped_state_files_give_valueerror_or_a_valid_stream(data):
    buf = io.BytesIO()
    trained().save(buf)
    raw = bytearray(buf.getvalue())
    if data.draw(st.booleans(), label="truncate"):
        raw = raw[: data.draw(st.integers(0, len(raw) - 1), label="length")]
    else:
        for _ in range(data.draw(st.integers(1, 4), label="flips")):
            raw[data.draw(st.integers(0, len(raw) - 1), label="at")] = data.draw(st.integers(0, 255), label="byte")
    try:
        est = StreamingMKC.load(io.BytesIO(bytes(raw)))
    except ValueError:
        return
    X, Y = linear(7, 20)
    assert set(est.learn_many(X, Y).tolist()) <= VALID_STATUS


# -- item 3: constructors ----------------------------------------------------------------------

nan, inf = float("nan"), float("inf")
BAD_STREAMS = [
    (dict(n=3.5), "n must be an integer"),
    (dict(window=MAX_WINDOW + 1), "largest supported"),
    (dict(window=2), "must hold at least n"),
    (dict(estep_every=0), "estep_every must be >= 1"),
    (dict(estep_every=2.5), "estep_every must be an integer"),
    (dict(m=10**6, window=4096), "MiB"),
    (dict(sigma=nan), "sigma must be finite and > 0"),
    (dict(sigma=inf), "sigma must be finite and > 0"),
    (dict(sigma=[1.0, 2.0]), "one value per channel"),
    (dict(d=nan), "d must be finite and > 0"),
    (dict(d=0.0), "d must be finite and > 0"),
    (dict(theta0=[1.0, 2.0]), "theta0 must be 3 finite numbers"),
    (dict(theta0=[nan, 1.0, 2.0]), "theta0 must be 3 finite numbers"),
    (dict(fp_rounds=0), "fp_rounds must be >= 1"),
    (dict(estep_max_iter=-1), "estep_max_iter must be >= 0"),
    (dict(min_samples=-5), "min_samples must be >= 0"),
    (dict(refactor_every=-1), "refactor_every must be >= 0"),
    (dict(sigma_hi=inf), "sigma_hi must be a finite number"),
    (dict(d_hi=inf), "d_hi must be a finite number"),
    (dict(a_factor=nan), "a_factor must be a finite number"),
    (dict(a_factor=0.0), "a_factor must be > 0"),
    (dict(a=nan), "a must be a finite number"),
    (dict(estep_gtol=nan), "estep_gtol must be a finite number"),
    (dict(fp_tol=-1.0), "fp_tol must be >= 0"),
    (dict(sigma_start=0.0), "sigma_start must be > 0"),
    (dict(sigma_pull=inf), "sigma_pull must be a finite number"),
]


@pytest.mark.parametrize("kw, message", BAD_STREAMS)
def test_streaming_mkc_refuses_absurd_arguments(kw, message):
    kw = {"n": 3, "m": 1, **kw}
    with pytest.raises(ValueError, match=message):
        StreamingMKC(kw.pop("n"), kw.pop("m"), **kw)


def test_mag_calibrator_default_init_samples():
    assert MagCalibrator(window=32, estep_every=8, init_samples=0).init_samples == 32
    assert MagCalibrator(window=256, init_samples=None).init_samples == 64
    assert MagCalibrator(window=256, init_samples=np.int64(256)).init_samples == 256


def test_sensible_edge_arguments_still_work():
    # estep_every > window: one E-step, then add/remove only (tests/test_stream.py relies on it)
    est = StreamingMKC(3, 1, window=W, estep_every=10**9, a=0.0)
    X, Y = linear(8, 100)
    assert est.learn_many(X, Y)[-1] == 0
    assert np.linalg.norm(est.theta - THETA) < 0.05
    assert isinstance(StreamingMKC(np.int64(3), 1, window=np.int64(64)).config.window, int)


@pytest.mark.parametrize("kw, message", [
    (dict(window=MAX_WINDOW + 1), "largest supported"),
    (dict(window=8), "must hold at least n = 9"),
    (dict(estep_every=0), "estep_every must be >= 1"),
    (dict(window=64, estep_every=65), "estep_every 65 must be <= window 64"),
    (dict(init_samples=-5), "init_samples must be an integer"),
    (dict(init_samples=10**6), "init_samples must be an integer"),
    (dict(unit=None), "unit must be a string"),
    (dict(rules=None), "rules must be an AcceptanceRules"),
    (dict(policy="lifo"), "policy must be one of"),
    (dict(sigma=nan), "sigma must be finite"),
])
def test_mag_calibrator_refuses_absurd_arguments(kw, message):
    with pytest.raises(ValueError, match=message):
        MagCalibrator(**kw)


@pytest.mark.parametrize("kw", [dict(min_coverage=nan), dict(min_coverage=1.5), dict(max_condition=nan),
                                dict(max_outlier_fraction=-0.1), dict(max_residual_rel=0.0),
                                dict(max_disagreement_rel=nan), dict(field_range_ut=(100.0, 10.0)),
                                dict(field_range_ut=(nan, 100.0)), dict(field_range_ut=(15.0,))])
def test_acceptance_rules_refuse_nan_and_inverted_thresholds(kw):
    with pytest.raises(ValueError, match=f"AcceptanceRules.{next(iter(kw))} out of range"):
        AcceptanceRules(**kw)


def test_acceptance_rules_allow_no_upper_limit():
    assert AcceptanceRules(max_condition=inf, field_range_ut=(0.0, inf)).max_condition == inf


@pytest.mark.parametrize("kw, message", [
    (dict(max_em_iter=-1), "max_em_iter must be an integer >= 0"),    # wrote outside its history arrays
    (dict(max_em_iter=nan), "max_em_iter must be an integer"),
    (dict(max_iter=0), "max_iter must be an integer >= 1"),
    (dict(em_tol=nan), "em_tol must be a finite number"),
    (dict(tol=nan), "tol must be a finite number"),
    (dict(a_factor=nan), "a_factor must be a finite number > 0"),
    (dict(estep_max_iter=-1), "estep_max_iter must be an integer"),
    (dict(estep_gtol=nan), "estep_gtol must be a finite number"),
    (dict(sigma_pull=-1.0), "sigma_pull must be a finite number >= 0"),
    (dict(a=inf), "a must be a finite number > 0"),
    (dict(sigma_bounds=(0.05, inf)), "bounds must satisfy"),
    (dict(d_bounds=(1e-9, inf)), "bounds must satisfy"),
    (dict(sigma_bounds=5.0), "must be .lo, hi. pairs"),
])
def test_mkc_regressor_refuses_absurd_arguments_at_fit(kw, message):
    X, Y = linear(9, 100)
    with pytest.raises(ValueError, match=message):
        MKCRegressor(**kw).fit(X[:, 0, :], Y[:, 0])


# -- item 4: gross spikes and the geometry check -------------------------------------------------

SPIKE_DIR = np.array([0.6, -0.64, 0.48])


@pytest.fixture(scope="module")
def bursty():
    s = synthetic_mag(seed=1, N=2000)          # 10% bursts: where one spike used to flatten the weights
    return s, fit_ellipsoid(np.delete(s.raw, 777, axis=0), "mkc-em")


@pytest.mark.parametrize("size", [5e5, 8e5, 1e6, 1e12, 1e300])
def test_one_gross_spike_neither_fakes_a_line_nor_leaks_into_the_fit(bursty, size):
    """Before: 1e6 uT made the batch fit reject 'the samples lie on a line' (seed 1) and
    5e5-8e5 uT were accepted 1.8-2.3 uT off; now the spike is left out and counted."""
    s, spike_free = bursty
    raw = s.raw.copy()
    raw[777] += size * SPIKE_DIR
    fit = fit_ellipsoid(raw, "mkc-em")
    assert fit.quality["gross_outliers"] == 1
    assert fit.weights.shape == (2000,) and fit.weights[777] == 0.0
    np.testing.assert_allclose(fit.hard_iron, spike_free.hard_iron, rtol=0, atol=1e-9)
    assert abs(fit.field - spike_free.field) < 1e-9
    assert np.linalg.norm(fit.hard_iron - s.hard_iron) < 0.1
    assert fit.quality["outlier_fraction"] >= 1 / 2000            # the spike counts as an outlier
    assert json.loads(json.dumps(fit.to_json()))["quality"]["gross_outliers"] == 1


def test_fixed_kernel_mkc_leaves_gross_spikes_out_and_least_squares_sees_the_data_as_given(bursty):
    s, _ = bursty
    raw = s.raw.copy()
    raw[777] += 1e6 * SPIKE_DIR
    mkc = fit_ellipsoid(raw, "mkc")
    assert mkc.quality["gross_outliers"] == 1
    np.testing.assert_allclose(mkc.hard_iron, fit_ellipsoid(np.delete(s.raw, 777, axis=0), "mkc").hard_iron, atol=1e-9)
    clean_ls = fit_ellipsoid(s.raw, "ls")
    assert clean_ls.quality["gross_outliers"] == 0
    try:                                # the baseline is not cleaned: the spike wrecks or breaks it
        ls = fit_ellipsoid(raw, "ls")
    except MKCInputError as exc:        # (EllipsoidError is one)
        assert "singular" in str(exc) or "ellipsoid" in str(exc)
        return
    assert ls.quality["gross_outliers"] == 0
    assert np.linalg.norm(ls.hard_iron - s.hard_iron) > 5.0


def test_configuration_errors_are_input_errors_for_the_cli():
    """The CLI turns MKCInputError into exit 2 with a one-line message (not a traceback)."""
    with pytest.raises(MKCInputError, match="largest supported"):
        MagCalibrator(window=MAX_WINDOW + 1)
    with pytest.raises(MKCInputError, match="AcceptanceRules.min_coverage"):
        AcceptanceRules(min_coverage=nan)


def test_a_handful_of_spikes_is_left_out():
    s = synthetic_mag(seed=2, N=2000)
    raw = s.raw.copy()
    idx = [5, 400, 1100, 1500, 1999]
    raw[idx] += np.outer([1e6, -3e5, 2e7, 1e9, 5e5], SPIKE_DIR)
    fit = fit_ellipsoid(raw, "mkc-em")
    assert fit.quality["gross_outliers"] == 5 and np.all(fit.weights[idx] == 0)
    assert np.linalg.norm(fit.hard_iron - s.hard_iron) < 0.15


def test_no_gross_outliers_in_a_clean_or_mostly_still_recording():
    s = synthetic_mag(seed=3, N=2000, spike_fraction=0.0)
    assert not gross_outlier_mask(s.raw).any()
    fit = fit_ellipsoid(s.raw, "mkc-em")
    assert fit.quality["gross_outliers"] == 0
    # 85% still (like the BROAD excerpt, 72%): the rotation's samples are not "gross"
    rng = np.random.default_rng(0)
    still = s.raw[0] + 0.05 * rng.normal(size=(1700, 3))
    assert not gross_outlier_mask(np.concatenate([still, s.raw[::7][:300]])).any()


def _planar(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([50 * np.cos(ph) + 10, 50 * np.sin(ph) - 5, np.full(n, 20.0)], 1) + 0.01 * rng.normal(size=(n, 3))


@pytest.mark.parametrize("spike", [None, 250.0, 1e3, 1e6])
def test_planar_data_is_still_rejected_with_or_without_spikes(spike):
    """A plane stays a plane: off-plane spikes (beyond 3 distance quantiles) used to make it look
    three-dimensional, and a 1e6 one turned it into 'a line'."""
    raw = _planar()
    if spike is not None:
        raw[[5, 500, 1500]] += [0.0, 0.0, spike]
    with pytest.raises(EllipsoidError, match="lie on a plane.*rotate the sensor"):
        fit_ellipsoid(raw, "mkc-em")


@pytest.mark.parametrize("spike", [None, 1e6])
def test_collinear_data_is_still_rejected(spike):
    rng = np.random.default_rng(1)
    raw = np.stack([np.linspace(-50, 50, 2000), np.zeros(2000), np.zeros(2000)], 1) + 0.01 * rng.normal(size=(2000, 3))
    if spike is not None:
        raw[7] += [0.0, spike, 0.0]
    with pytest.raises(EllipsoidError, match="lie on a line.*rotate the sensor"):
        fit_ellipsoid(raw, "mkc-em")
