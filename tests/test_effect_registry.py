"""The effect library is one registry: each effect declares its forward model and its diagnosis
form together, the diagnoser's FORMS only index them, a mean form's columns reproduce its own
forward model, and the synthetic calibration stream is a preset of the simulator."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.diagnose.forms import FORMS
from mkc_stream.sim.effects import EFFECTS, FAMILIES, STAGES, SimContext
from mkc_stream.sim.effects.form import EstimatedForm, MeanForm
from mkc_stream.sim.presets import sweep


def test_every_effect_declares_one_form_and_the_diagnoser_reads_it():
    names = [e.name for module in FAMILIES for e in module.EFFECTS]
    assert len(names) == len(set(names)) == len(EFFECTS), "two effects share a name"
    assert list(FORMS) == list(EFFECTS)
    for name, effect in EFFECTS.items():
        form = effect.form
        assert FORMS[name] is form
        assert effect.stage in STAGES
        if isinstance(form, MeanForm):
            assert effect.kind == "mean" and form.k > 0, name
        else:
            assert isinstance(form, EstimatedForm), f"{name}: form is {type(form).__name__}"
            assert effect.kind == form.kind in ("noise", "clock", "mask"), name
            assert (form.mask is not None) == (form.kind == "mask"), name
        if form.alias_of is not None:
            assert form.alias_of in EFFECTS and form.alias_of != name
            assert EFFECTS[form.alias_of].kind == effect.kind


def _scene(n=600, seed=0):
    """A sensor turning through random directions with temperature and current columns, the raw
    magnetometer before any effect, and the diagnoser's view a form reads (recording in uT)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1                                         # s
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    b = np.array([10.0, -5.0, 3.0])                                # uT
    B = 50.0 * u
    aux = {"temp": 25.0 + 6.0 * np.sin(t / 5.0), "current": 3.0 + 2.0 * np.cos(t / 3.0)}
    m0 = B + b
    env = SimpleNamespace(frame=SimpleNamespace(t=t, m=m0, aux=aux, duration=float(t[-1] - t[0]), unit="uT"),
                          cache={}, to_uT=1.0, F_ref=50.0)
    ctx = SimContext(t=t, B=B.copy(), m=m0.copy(), aux=aux, b=b, S=np.eye(3), F=50.0, rng=rng,
                     t_out=t.copy(), keep=np.ones(n, dtype=bool))
    return ctx, env, SimpleNamespace(b=b, S=np.eye(3))


#: (effect, its parameters, the form's design, theta in the form's units (the recording's, uT))
LINEAR_CASES = [
    ("hard_iron_drift", {"vx": 0.6, "vy": -0.4, "vz": 0.2}, {}, [0.6, -0.4, 0.2]),
    ("current_hard_iron", {"kx": 0.2, "ky": -0.1, "kz": 0.05}, {}, [0.2, -0.1, 0.05]),
    ("temperature_offset", {"cx": 30.0, "cy": -12.0, "cz": 8.0, "tau": 0.0, "t_ref": 20.0},
     {"tau": 0.0, "tau2": 0.0}, [0.030, -0.012, 0.008]),                       # nT/degC -> uT/degC
    ("hard_iron_step", {"dx": 1.5, "dy": -0.7, "dz": 0.4, "t_step": 30.05}, {"t_step": 30.05}, [1.5, -0.7, 0.4]),
    ("scale_nonlinearity", {"bx": 200.0, "by": -150.0, "bz": 90.0}, {}, [0.2, -0.15, 0.09]),   # nT -> uT
]


@pytest.mark.parametrize("name,params,design,theta", LINEAR_CASES, ids=[c[0] for c in LINEAR_CASES])
def test_a_mean_form_reproduces_its_forward_model(name, params, design, theta):
    """The change the forward model makes equals the form's G theta up to a constant per axis
    (what the fitted hard iron absorbs): forward model and form, declared together, agree in
    shape and units."""
    ctx, env, state = _scene()
    m0 = ctx.m.copy()
    EFFECTS[name].apply(ctx, params)
    G = EFFECTS[name].form.G(env, design)(env.frame, m0, state)
    rest = (ctx.m - m0) - G @ np.asarray(theta)
    assert np.ptp(ctx.m - m0, axis=0).min() > 1e-3                 # the effect is there to be matched (uT)
    np.testing.assert_allclose(rest - rest.mean(axis=0), 0.0, atol=1e-9)


SWEEPS = [dict(seed=0), dict(seed=3, N=1500, burst_fraction=0.25), dict(seed=4, N=500, burst_fraction=0.0),
          dict(seed=6, spike_fraction=0.05, spike_magnitude=200.0, burst_fraction=0.3),
          dict(seed=8, N=1200, field=30.0, noise=1.0, hard_iron_scale=100.0, soft_spread=0.5, rate_hz=100.0,
               burst_length=(5, 10), burst_magnitude=(1.0, 3.0))]


@pytest.mark.parametrize("kw", SWEEPS, ids=lambda kw: f"seed{kw['seed']}")
def test_synthetic_mag_is_the_simulators_sweep_preset(kw):
    """Same arguments, same samples and truth: the written-out generator and the simulator
    draw the same numbers in the same order (compared in one process)."""
    s, p = synthetic_mag(**kw), sweep(**kw)
    np.testing.assert_array_equal(p.mag_full, s.raw)
    np.testing.assert_array_equal(p.recording.mag, s.raw)
    np.testing.assert_array_equal(p.recording.t, s.t)
    np.testing.assert_array_equal(p.truth["hard_iron"], s.hard_iron)
    np.testing.assert_array_equal(p.truth["soft_iron"], s.soft_iron)
    np.testing.assert_array_equal(p.truth["disturbed"], s.disturbed)
    np.testing.assert_array_equal(p.truth["directions"], s.directions)
    assert p.truth["field"] == s.field


def test_the_sweep_preset_takes_library_effects():
    """A library effect lands on top of the same stream: a drift of v uT/h adds v (t - t0) / 3600 s."""
    v = np.array([0.5, -0.3, 0.2])
    s = synthetic_mag(seed=2, N=800)
    p = sweep(seed=2, N=800, effects=[("hard_iron_drift", dict(zip(("vx", "vy", "vz"), v)))])
    np.testing.assert_allclose(p.mag_full - s.raw, np.outer((s.t - s.t[0]) / 3600.0, v), atol=1e-12)
