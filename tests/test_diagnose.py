"""Sim-to-real gap diagnosis: no effect -> no gap; a strong effect is named first, closes the
gap on held-out blocks and is measured in natural units; effects a recording cannot reveal are
"not testable"; bad input gives clear errors; the command writes the spec's JSON and a report."""
import json

import numpy as np
import pytest

from mkc_stream.cli import main
from mkc_stream.diagnose import DiagnoseError, diagnose
from mkc_stream.diagnose.report import text
from mkc_stream.io.recording import Recording, bundled_recording, read_recording
from mkc_stream.sim import EFFECTS, SensorModel, generate, simulate

SPEC_KEYS = {"verdict", "gap_before", "gap_after", "where", "effects", "ambiguous_with"}
EFFECT_KEYS = {"name", "testable", "selected", "shrink", "shrink_ci", "magnitude", "magnitude_ci"}
K_CURRENT = np.array([0.08, -0.05, 0.03])      # uT/A


@pytest.fixture(scope="module")
def trajectory():
    return generate("hand", duration=300, rate=20, seed=11, power=True)


@pytest.fixture(scope="module")
def clean(trajectory):
    return simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), seed=12).recording


@pytest.fixture(scope="module")
def with_current(trajectory):
    kx, ky, kz = K_CURRENT
    eff = [("current_hard_iron", {"kx": kx, "ky": ky, "kz": kz})]
    return simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=12).recording


def test_no_effect_gives_no_gap(clean):
    d = diagnose(clean, replicas=24)
    assert d.verdict == "no_gap", (d.gap_before, d.threshold)
    assert 0.5 < d.gap_before < d.threshold
    assert d.info["matched_tests"]["fired"] == [] and d.info["detected_by"] is None
    obj = json.loads(json.dumps(d.to_json(), allow_nan=False))
    assert SPEC_KEYS <= set(obj)
    assert {e["name"] for e in obj["effects"]} == set(EFFECTS)
    for e in obj["effects"]:
        assert EFFECT_KEYS <= set(e) and e["selected"] is False
        assert e["status"] in ("not selected", "no estimate", "not testable")


def test_strong_effect_named_first_with_magnitude(with_current, tmp_path, capsys):
    path = tmp_path / "current.csv"
    with_current.write(path)
    js, rep = tmp_path / "out.json", tmp_path / "report"
    code = main(["diagnose", str(path), "--json", str(js), "--report", str(rep), "--replicas", "24"])
    text = capsys.readouterr().out
    obj = json.loads(js.read_text())
    assert code == 0 and "EXPLAINED" in text and "current_hard_iron" in text
    assert obj["verdict"] == "explained" and obj["selected"][0] == "current_hard_iron"
    assert obj["gap_after"] < obj["gap_before"]
    first = obj["effects"][0]
    assert first["name"] == "current_hard_iron" and first["selected"]
    assert first["shrink"] >= 0.7 and len(first["shrink_ci"]) == 2
    assert first["magnitude"]["unit"] == "uT/A"
    assert first["magnitude"]["value"] == pytest.approx(np.linalg.norm(K_CURRENT), rel=0.1)
    lo, hi = first["magnitude_ci"]["value"]
    assert lo <= first["magnitude"]["value"] <= hi
    assert obj["where"] and {"family", "channel", "bin", "z"} <= set(obj["where"][0])
    assert (rep / "report.md").exists() and (rep / "residual_time.png").exists()
    assert (rep / "sphere.png").exists() and (rep / "spectrum.png").exists() and (rep / "aux_current.png").exists()


def test_not_testable_without_aux_or_accelerometer(clean):
    mag_only = Recording(t=clean.t[:3000], mag=clean.mag[:3000], meta={"units.mag": "uT"})
    d = diagnose(mag_only, replicas=16)
    res = {r.name: r for r in d.effects}
    for name, word in (("temperature_offset", "'temp'"), ("current_hard_iron", "'current'"),
                       ("throttle_hard_iron", "'throttle'"), ("misalignment", "accelerometer"),
                       ("latency", "accelerometer")):
        assert not res[name].testable and res[name].status == "not testable"
        assert word in res[name].reason
    assert all(r.status != "absent" for r in d.effects)
    obj = d.to_json()
    assert all(e["shrink"] is None for e in obj["effects"] if not e["testable"])


def test_bad_input_is_refused_clearly(clean, tmp_path, capsys):
    with pytest.raises(DiagnoseError, match="too short"):
        diagnose(Recording(t=clean.t[:400], mag=clean.mag[:400]))
    mag = clean.mag[:2000].copy()
    mag[5] = np.nan
    with pytest.raises(DiagnoseError, match="non-finite"):
        diagnose(Recording(t=clean.t[:2000], mag=mag))
    with pytest.raises(ValueError, match="unknown effect"):
        diagnose(clean, exclude=["nope"])
    short = tmp_path / "short.csv"
    Recording(t=clean.t[:300], mag=clean.mag[:300]).write(short)
    assert main(["diagnose", str(short)]) == 2
    assert "too short" in capsys.readouterr().err
    # rows with NaN are skipped by the reader, reported, and the diagnosis still runs
    path = tmp_path / "nan.csv"
    Recording(t=clean.t[:1500], mag=clean.mag[:1500]).write(path)
    lines = path.read_text().splitlines()
    lines[10] = "1.0,nan,2,3"
    path.write_text("\n".join(lines) + "\n")
    rec = read_recording(path)
    assert len(rec.bad_rows) == 1
    code = main(["diagnose", str(path), "--replicas", "8", "--json", "-"])
    captured = capsys.readouterr()
    assert code in (0, 1) and "bad rows" in captured.err
    assert json.loads(captured.out)["info"]["bad_rows"] == 1


def test_real_recording_quantization_is_found():
    """The bundled QMC5883L recording (integer counts): its raw values lie on a lattice the
    plain simulator lacks, and the diagnosis measures its step."""
    rec = bundled_recording()
    d = diagnose(Recording(t=rec.t[:5000], mag=rec.mag[:5000], meta=rec.meta), replicas=16)
    assert d.verdict != "no_gap"
    q = {r.name: r for r in d.effects}["quantization"]
    assert q.magnitude is not None and q.magnitude["unit"] == "counts"
    assert q.magnitude["value"] == pytest.approx(round(q.magnitude["value"]), abs=1e-6)
    assert any(w["family"] == "raw" for w in d.to_json()["where"]) or q.shrink > 0


def test_physical_range_prior():
    """A fit far outside the library's realistic range is no explanation (it is reported with
    status "implausible" and never selected): e.g. a current-induced offset absorbed as
    thousands of nT/degC of thermal offset."""
    from mkc_stream.diagnose.forms import implausible, prior_bound

    absurd = {"value": 4010.0, "unit": "nT/degC", "vector": [3000.0, 2000.0, 1800.0]}
    fine = {"value": 40.0, "unit": "nT/degC", "vector": [30.0, 20.0, 18.0]}
    assert implausible("temperature_offset", absurd) and not implausible("temperature_offset", fine)
    assert prior_bound("temperature_offset", fine)[0] == pytest.approx(3 * 50 * np.sqrt(3))
    assert prior_bound("current_hard_iron", {"value": 1.0, "unit": "counts/A"}) is None   # unknown unit


def test_quartic_statistic_sees_scale_nonlinearity():
    """The u_j^4 pattern a per-axis scale nonlinearity leaves in the field strength is orthogonal
    to what an ellipsoid absorbs, and a cubic departure of 200 nT shows in it at many sigma."""
    from mkc_stream.diagnose.panel import quartic_basis

    rng = np.random.default_rng(0)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    Q = quartic_basis(u, u)
    A = np.column_stack([np.ones(len(u)), u] + [u[:, i] * u[:, j] for i in range(3) for j in range(i, 3)])
    assert np.abs(A.T @ Q).max() < 1e-6 * len(u)
    beta = 0.2                                                     # uT departure per axis at the field
    r = -beta * np.sum(u ** 4, axis=1) + 0.1 * rng.normal(size=len(u))   # norm residual, 0.1 uT noise
    z = (Q.T @ r) / np.sqrt(np.sum(Q * Q, axis=0)) / 0.1
    assert np.all(np.abs(z) > 10)


def _slow(trajectory, name, v):
    keys = ("vx", "vy", "vz") if name == "hard_iron_drift" else ("cx", "cy", "cz")
    eff = [(name, dict(zip(keys, v * np.array([0.6, -0.64, 0.48]))))]
    return simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=12).recording


def test_slow_drift_found_by_its_matched_test(trajectory):
    """A hard-iron drift of 0.6 uT/h over 5 min (0.05 uT, half the noise) is below the gap
    index's alarm, but its matched test (a score test calibrated on the replicas) fires: the
    drift is named first, the thermal offset and step that can mimic a trend are reported as
    ambiguous rather than chosen, and the magnitude is measured."""
    d = diagnose(_slow(trajectory, "hard_iron_drift", 0.6), replicas=24)
    assert d.gap_before <= d.threshold                  # the omnibus index alone misses it
    assert d.info["detected_by"] == "matched tests" and "hard_iron_drift" in d.info["matched_tests"]["fired"]
    assert d.verdict == "explained" and d.selected[0] == "hard_iron_drift"
    r = {e.name: e for e in d.effects}["hard_iron_drift"]
    assert r.shrink >= 0.7
    assert r.magnitude["unit"] == "uT/h" and r.magnitude["value"] == pytest.approx(0.6, rel=0.25)
    json.dumps(d.to_json(), allow_nan=False)


def test_thermal_offset_under_ramp_is_ambiguous_with_drift():
    """Under a temperature ramp a thermal offset and a drift have the same observable: when only
    the matched tests see it, each explains the other's evidence away and both are reported
    (selected + ambiguous_with)."""
    traj = generate("hand", duration=300, rate=20, seed=11, power=True, temp="ramp")
    d = diagnose(_slow(traj, "temperature_offset", 6.5), replicas=24)
    assert d.info["detected_by"] == "matched tests" and d.verdict != "no_gap"
    assert {"temperature_offset", "hard_iron_drift"} <= set(d.selected + d.ambiguous_with)


def test_block_mean_shares_match_their_double_sums():
    """The variance of a block mean of a Gauss-Markov process (closed form) and of its projection
    on a turning sensor's direction (per block, by forward/backward recursions) equal the brute
    double sums they stand for; a turning sensor sees much less of a slow noise's block mean."""
    from types import SimpleNamespace

    from mkc_stream.diagnose.forms import _block_mean_share_norm, block_mean_share

    dt, n = 0.05, 400
    for tau in (0.3, 5.0, 80.0):
        k = np.arange(n)
        rho = np.exp(-np.abs(k[:, None] - k[None, :]) * dt / tau)
        # the continuous-time closed form against the sampled double sum (n = 400 samples)
        assert block_mean_share(n * dt, tau) == pytest.approx(rho.mean(), rel=0.03)
    rng = np.random.default_rng(3)
    lon = np.linspace(0, 4 * np.pi, 2 * n) + 0.1 * rng.normal(size=2 * n)    # waved round twice a block
    lat = 0.6 * np.sin(np.linspace(0, 6 * np.pi, 2 * n))
    v = np.stack([np.cos(lon) * np.cos(lat), np.sin(lon) * np.cos(lat), np.sin(lat)], 1)
    S = np.diag([1.1, 0.9, 1.0])
    frame = SimpleNamespace(dt0=dt, block_slices=lambda: [slice(0, n), slice(n, 2 * n)])
    env = SimpleNamespace(frame=frame, base=SimpleNamespace(fit=SimpleNamespace(v=v, state=SimpleNamespace(S=S))),
                          cache={})
    u = v @ S
    for tau in (0.3, 5.0, 80.0):
        k = np.arange(n)
        rho = np.exp(-np.abs(k[:, None] - k[None, :]) * dt / tau)
        want = np.mean([np.sum((u[sl] @ u[sl].T) * rho) / n ** 2 for sl in frame.block_slices()])
        assert _block_mean_share_norm(env, np.ones(2), tau) == pytest.approx(want, rel=1e-9)
    assert _block_mean_share_norm(env, np.ones(2), 80.0) < 0.5 * block_mean_share(n * dt, 80.0)


def test_white_share_of_a_gauss_markov_noise_is_what_third_differences_read():
    """colored_white_share (the part of a Gauss-Markov noise the baseline's third-difference
    white-noise estimate holds) against a simulated AR(1): var(d3 x) / (20 var x)."""
    from scipy.signal import lfilter

    from mkc_stream.diagnose.forms import colored_white_share

    rng = np.random.default_rng(5)
    dt, n = 0.05, 400_000
    for tau in (0.05, 0.5, 5.0):
        rho = np.exp(-dt / tau)
        x = lfilter([1.0], [1.0, -rho], rng.normal(size=n) * np.sqrt(1 - rho ** 2))
        got = np.var(np.diff(x, 3)) / (20 * np.var(x))
        assert colored_white_share(dt, tau) == pytest.approx(got, rel=0.05, abs=2e-4)
    assert colored_white_share(dt, 1e-9) == pytest.approx(1.0)


def test_bursts_are_not_made_of_a_coloured_noise_peaks():
    """A coloured noise three times the white core turns faster than the running median follows;
    its peaks are not bursts. Five real 25-sigma bursts are still found, with their length. (With
    the cut at 4 sigma of the core, the noise's peaks were counted as bursts by the hundred and
    put into every replica on top of the noise that made them.)"""
    from mkc_stream.diagnose.baseline import estimate_bursts
    from mkc_stream.sim.effects.noise import gauss_markov

    rng = np.random.default_rng(3)
    n = 20000
    e = rng.normal(size=n) + 3.0 * gauss_markov(rng, np.arange(n) * 0.05, 1.0, 1.0, dims=1)[:, 0]
    for a in rng.choice(np.arange(200, n - 200, 1000), size=5, replace=False):
        e[a:a + 30] += 25.0
    b = estimate_bursts(e, np.ones(n, dtype=bool), 1.0)
    assert b["count"] == 5
    assert b["fraction"] == pytest.approx(150 / n, rel=0.2)


def test_strong_coloured_noise_is_named_with_its_amplitude(trajectory):
    """0.25 uT of Gauss-Markov noise (20 s) against 0.08 uT of white noise: a slow noise several
    times the kernel's core. Named first, with its amplitude within 25%. Before the noise
    estimators read the samples beyond 4 core sigma and the burst model stopped making bursts
    of its peaks, the fit was 46% low and the verdict "unexplained"."""
    eff = [("colored_noise", {"sigma": 0.25, "tau": 20.0})]
    rec = simulate(trajectory, SensorModel(noise=0.08, burst_fraction=0.01), effects=eff, seed=12).recording
    d = diagnose(rec, replicas=24)
    assert d.selected[0] == "colored_noise"
    # "explained" only with the held-out gap index at or below its alarm (the verdict's own numbers)
    assert d.verdict == ("explained" if d.gap_after <= d.threshold else "partially_explained")
    r = {e.name: e for e in d.effects}["colored_noise"]
    assert r.magnitude["value"] == pytest.approx(0.25, rel=0.25)


@pytest.mark.slow  # ~30 s; CI keeps the coloured-noise route with the strong single component above
def test_two_time_scale_coloured_noise_is_found_with_both_components(trajectory):
    """Coloured noise with a fast (1 s) and a slow (60 s) Gauss-Markov component, 0.1 uT each
    against 0.1 uT of white noise: coloured noise is named, closes the gap, and its fit holds two
    components a decade or more apart, with the total within 30%. (Their correlation times are
    loosely pinned in 5 minutes: the fit put them at 0.27 s and 7.9 s.)"""
    eff = [("colored_noise", {"sigma": 0.1, "tau": 1.0}), ("colored_noise", {"sigma": 0.1, "tau": 60.0})]
    rec = simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=12).recording
    d = diagnose(rec, replicas=24)
    assert d.selected[0] == "colored_noise"
    assert d.verdict == ("explained" if d.gap_after <= d.threshold else "partially_explained")
    r = {e.name: e for e in d.effects}["colored_noise"]
    assert r.shrink >= 0.7
    comps = r.magnitude["components"]
    taus = sorted(t for s, t in comps if s > 0.03)
    assert len(taus) == 2 and taus[1] >= 10 * taus[0]
    assert r.magnitude["value"] == pytest.approx(np.hypot(0.1, 0.1), rel=0.3)


@pytest.mark.slow  # ~27 s; CI keeps the coloured-noise route with the strong single component above
def test_flicker_like_coloured_noise_is_named():
    """A flicker-like noise as the blind benchmark injects it: three Gauss-Markov components at
    0.5, 5 and 30 s, 0.09 uT each, against 0.1 uT of white noise, over 500 s. Coloured noise is
    named and closes the gap. With only the first (two-component, baseline-weighted) estimate
    it closed 0.94, short of the catch-all's 0.95, and the verdict was "unexplained"; the
    refined three-component estimate wins on the gap index."""
    traj = generate("hand", duration=500, rate=20, seed=11, power=True)
    eff = [("colored_noise", {"sigma": 0.09, "tau": t}) for t in (0.5, 5.0, 30.0)]
    rec = simulate(traj, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=14).recording
    d = diagnose(rec, replicas=24)
    assert d.verdict == "explained" and d.selected[0] == "colored_noise", (d.verdict, d.selected)
    r = {e.name: e for e in d.effects}["colored_noise"]
    assert r.shrink >= 0.95
    assert r.magnitude["value"] == pytest.approx(0.09 * np.sqrt(3), rel=0.3)


@pytest.mark.slow  # ~28 s; CI keeps the current's route in test_diagnose_attitude.py and the blind subset
def test_throttle_standing_in_for_a_removed_current_effect_is_only_partial(trajectory):
    """A weak current hard iron (0.02 uT/A) with the current's own effect removed from the
    library: the throttle law absorbs the part of the current that follows the throttle and
    brings the gap index to its null level, but the other loads' share stays in the residual.
    The completeness test (residual against each aux signal, given the selected effects) sees
    it: "partially explained", naming the current (and the voltage, which sags with it), not
    "explained". Before that test the verdict was "explained" by throttle_hard_iron."""
    eff = [("current_hard_iron", dict(zip(("kx", "ky", "kz"), 0.02 * np.array([0.6, -0.64, 0.48]))))]
    rec = simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=12).recording
    d = diagnose(rec, exclude=["current_hard_iron"], replicas=24)
    assert d.verdict == "partially_explained" and d.selected[0] == "throttle_hard_iron", (d.verdict, d.selected)
    left = d.info["aux_left"]
    # the battery's voltage sags with the current, so it may be named too
    assert "current" in left["still_followed"] and left["tests"]["current"]["t"] > 3.0
    assert set(left["still_followed"]) <= {"current", "voltage"}
    assert "the residual still follows" in text(d) and "current (t = " in text(d)


def test_filtering_latency_is_explained_with_its_delay_and_spread(trajectory):
    """A magnetometer whose output filter delays it 15 ms and spreads it over +-40 ms: the
    filter averages directions a turn spreads apart, so besides the turn against the
    accelerometer (dip channel) the field strength drops at fast turns (norm channel, against
    the turn rate). The latency form's second-order strength term explains it (gap 3.8 -> 0.9,
    delay 21 ms, spread 34 ms); with the delay term alone this recording was unexplained."""
    eff = [("latency", {"delay": 15.0, "spread": 40.0})]
    rec = simulate(trajectory, SensorModel(noise=0.1, burst_fraction=0.01), effects=eff, seed=12).recording
    d = diagnose(rec, replicas=24)
    assert (d.where[0]["family"], d.where[0]["channel"]) == ("aux:turn_rate", "norm")
    assert d.verdict == "explained" and d.selected[0] == "latency"
    r = {e.name: e for e in d.effects}["latency"]
    assert r.shrink >= 0.7
    # each fold's fit sees half the blocks: the delay is read through the dip channel's
    # correlated accelerometer noise (+-4 ms here), hence the wide bounds
    assert r.magnitude["unit"] == "ms" and 7.5 < r.magnitude["value"] < 30.0
    assert 20.0 < r.magnitude["filter_spread_ms"] < 60.0


def test_every_mean_form_is_scaled_above_the_solvers_ridge(clean):
    """model._solve adds a ridge of RIDGE (1e-10) x the mean diagonal of the normal matrix, which the
    calibration's columns dominate. The ridge is on each Gauss-Newton step, so a parameter whose
    diagonal is D times the ridge keeps a fraction 1 / (1 + D) of its distance to the solution
    per step: harmless for D >= 100 after the fit's three steps, but the latency's filter
    variance in ms^2 (D ~ 0.01) stayed at 40 against 230. Every form's columns must be scaled
    well above it (the smallest here: the latency's delay per ms, D ~ 180)."""
    from mkc_stream.diagnose.baseline import fit_baseline
    from mkc_stream.diagnose.forms import FORMS, Env, MeanForm
    from mkc_stream.diagnose.frame import prepare
    from mkc_stream.diagnose.model import RIDGE, Term, _normal, fit_model

    frame = prepare(clean, 20000)
    base = fit_baseline(frame)
    env = Env(frame, base)
    checked = []
    for name, form in FORMS.items():
        designs = form.designs(env) if isinstance(form, MeanForm) else []
        if not designs:
            continue
        term = Term(name, designs[0], form.G(env, designs[0]), form.k)
        fit = fit_model(frame, base.fit.state, [term], base.valid, base.sigma, iters=0)
        A, _ = _normal(fit.X, fit.e, fit.inlier.astype(np.float64), base.sigma)
        ridge = RIDGE * np.trace(A) / A.shape[0]
        assert np.diag(A)[-form.k:].min() > 100.0 * ridge, name
        checked.append(name)
    assert len(checked) >= 12 and "latency" in checked


@pytest.mark.parametrize("args, message", [
    (["--lat", "10"], "--lat and --lon go together"),
    (["--lat", "95", "--lon", "3"], "must be <= 90"),
    (["--date", "2024-13-45"], "--date: date must be a decimal year or an ISO date"),
])
def test_diagnose_refuses_a_bad_field_reference(args, message, capsys):
    """The attitude-aided part's field reference is checked before any work (exit 2, the reason)."""
    assert main(["diagnose", "demo", *args]) == 2
    assert message in capsys.readouterr().err
