"""The hysteresis form's column (sim.effects.nonlinear.loop_column) and the play operator.

A ferromagnetic loop keeps its width at any rate of the field, so the column must depend on
where the field has been, not on how fast it moved; and a column regressed on residuals must
not read the sample whose noise the residual carries (one that did made the matched test fire on
a null recording with 0.6 uT of noise: decision 0034).
"""
import numpy as np
import pytest

from mkc_stream.sim.effects.nonlinear import loop_column
from mkc_stream.sim.effects.play import play_operator


def _field(n=3000, rate=20.0, noise=0.3, seed=0):
    t = np.arange(n) / rate
    m = np.stack([40 * np.sin(t / 3), 30 * np.cos(t / 2), 20 * np.sin(t / 5)], 1)
    return m + np.random.default_rng(seed).normal(0.0, noise, m.shape)


def test_the_play_trails_by_its_width_and_holds_for_twice_its_width_after_a_reversal():
    x = np.concatenate([np.linspace(0, 10, 101), np.linspace(10, 0, 101)[1:]])[:, None]
    y = play_operator(x, 0.5)
    assert np.allclose(y[10:101, 0] - x[10:101, 0], -0.5)              # rising: trails by w
    fall_x, fall_y = x[101:, 0], y[101:, 0]
    held = fall_x > 9.0                                                # the first 2 w of the fall
    assert held.sum() == 9 and np.allclose(fall_y[held], 9.5)         # holds at the top minus w
    assert np.allclose(fall_y[fall_x < 8.95] - fall_x[fall_x < 8.95], 0.5)   # then leads by w


@pytest.mark.parametrize("k", [0, 1, 2, 7, 1500, 2997, 2998, 2999])
def test_the_column_at_a_sample_does_not_read_that_sample(k):
    m = _field()
    before = loop_column(m, 0.1)
    m[k] += 5.0                                                        # 50 times the noise
    after = loop_column(m, 0.1)
    assert np.allclose(after[k], before[k], rtol=0, atol=1e-12)
    assert np.abs(after - before).max() > 0.5                         # its neighbours do read it


def test_the_column_depends_on_the_path_not_on_the_rate():
    m = _field(noise=0.0)
    assert np.array_equal(loop_column(m, 0.2), loop_column(m, 0.2))   # deterministic
    slow = np.repeat(m, 2, axis=0)                                     # the same path, half the speed
    c, c_slow = loop_column(m, 0.2), loop_column(slow, 0.2)
    moving = np.abs(np.gradient(m, axis=0)) > 0.05
    assert np.mean(np.sign(c[moving]) == np.sign(c_slow[::2][moving])) > 0.98
    rising = (np.gradient(m[:, 0]) > 0.2) & (np.arange(len(m)) > 0)     # no loop state before sample 0
    assert np.mean(np.isclose(c[rising, 0], -1.0)) > 0.97 and np.all(c[rising, 0] < 0)
