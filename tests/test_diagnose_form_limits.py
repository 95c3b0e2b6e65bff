"""A form's limit (MeanForm.limit): hysteresis is not claimed for a lag that grows with the rate.

A hysteresis loop's width does not depend on how fast the field moves; the hysteresis form's
limit, a lag in proportion to the field's rate, is a latency. When a latency is in the data
and the latency form is not in the library (the blind benchmark's "removed" trials), the hysteresis
form closed its whole gap and was claimed ("explained", wrong). The limit comparison must say
"lag" for a latency and stay quiet for a loop.
"""
import pytest

from mkc_stream.diagnose.baseline import fit_baseline
from mkc_stream.diagnose.engine import LIMIT_MARGIN, Engine
from mkc_stream.diagnose.forms import FORMS
from mkc_stream.diagnose.frame import prepare
from mkc_stream.diagnose.model import Term
from mkc_stream.sim import SensorModel, generate, simulate


def _hysteresis_choice(effects, seed):
    traj = generate("hand", duration=150, rate=20, seed=seed, power=True)
    rec = simulate(traj, SensorModel(noise=0.1), effects=effects, seed=seed + 1).recording
    frame = prepare(rec, 10_000)
    eng = Engine(frame, fit_baseline(frame), n_replicas=4)
    form = FORMS["hysteresis"]
    designs = form.designs(eng.env)
    term = Term("hysteresis", designs[0], form.G(eng.env, designs[0]), form.k,
                [(d, form.G(eng.env, d)) for d in designs])
    chosen = eng._choose([term], eng.base.valid, None)[0]
    cand = type("Cand", (), {"terms": [chosen]})()
    excess = eng._limit_cache[((), "hysteresis")]
    return chosen.design, excess, eng.limit_reason(cand, "hysteresis")


@pytest.mark.parametrize("seed", [3, 11])
def test_a_latency_is_a_lag_not_a_hysteresis_loop(seed):
    design, excess, why = _hysteresis_choice([("latency", {"delay": 12.0, "spread": 0.0})], seed)
    assert excess > LIMIT_MARGIN
    assert why is not None and "in proportion to the field's rate" in why and f"{excess:.0f}" in why


@pytest.mark.parametrize("seed", [3, 11])
def test_a_hysteresis_loop_is_not_taken_for_a_lag(seed):
    design, excess, why = _hysteresis_choice([("hysteresis", {"width": 0.2})], seed)
    assert why is None and excess < -LIMIT_MARGIN
    assert "w" in design                                  # a loop width, not the lag


def test_without_a_lag_or_a_loop_the_limit_says_nothing():
    design, excess, why = _hysteresis_choice([], 3)
    assert why is None and abs(excess) < LIMIT_MARGIN
