"""Deterministic candidates the held-out gap cannot rank: the matched evidence ranks them before
Occam does (decision 0029).

The case: the independent simulator's seed 4, trial 48, a 26 nT/degC thermal offset under a
temperature ramp. The gap index detects it; the offset (gap 0.947), a drift (0.972) and a step
(0.984) all close it and the bootstrap ties them, so the simplest, the drift, was named. Its matched
tests fired for all three, and the offset's term removes 1.02 of that evidence where the drift's
removes 0.62: they are not equivalent there.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from mkc_stream.diagnose import attribution
from mkc_stream.diagnose.attribution import TIE_FRACTION, Attribution
from mkc_stream.diagnose.matched import MatchedTests

OFFSET, DRIFT, STEP = "temperature_offset", "hard_iron_drift", "hard_iron_step"


class FakeMatched:
    """The matched tests' t values, unconditional and given other terms; fired and discrepancy
    are MatchedTests' own."""
    names = (OFFSET, DRIFT, STEP, "scale_nonlinearity")
    level = 1e-3

    def __init__(self, t):
        self.t = t                       # {(name, given): t}; given a sorted tuple

    def result(self, name, given=()):
        t = self.t.get((name, tuple(sorted(given))), 0.0)
        return {"t": t, "p": 1e-9 if t > 4.0 else 0.5}

    fired = MatchedTests.fired
    discrepancy = MatchedTests.discrepancy


# trial 48's tests, unconditional (as reported) and, given each candidate, what is left of the
# others' evidence; D = 6.27^2 + 4.04^2 + 5.13^2 = 81.7 over 3 tests
TRIAL_48 = {(OFFSET, ()): 6.27, (DRIFT, ()): 4.04, (STEP, ()): 5.13,
            (DRIFT, (OFFSET,)): 0.5, (STEP, (OFFSET,)): 0.3,
            (OFFSET, (DRIFT,)): 5.6, (STEP, (DRIFT,)): 3.1}


def _attribution(matched, gaps, cost, monkeypatch, boot_spread=0.05):
    """An Attribution whose candidates' held-out gaps are ``gaps``, each with its own bootstrap
    draws of spread ``boot_spread`` (0.05: the bootstrap cannot rank gaps 0.025 apart), and whose
    complexity is ``cost``."""
    att = Attribution.__new__(Attribution)
    att.matched = matched
    att.log = lambda s: None
    att.eng = SimpleNamespace(env=None)
    att._round_ref = SimpleNamespace(G=1.256)
    rng = np.random.default_rng(1)
    att.boot_gaps = lambda ev: ev.boot
    monkeypatch.setattr(attribution, "complexity", lambda n, cand, env: cost[n])
    full = {n: SimpleNamespace(G=g, cand=None, boot=g + rng.normal(0.0, boot_spread, 100)) for n, g in gaps.items()}
    return att, full


GAPS = {OFFSET: 0.947, DRIFT: 0.972, STEP: 0.984}
COST = {OFFSET: 8.2, DRIFT: 3.0, STEP: 9.0}


def test_the_matched_evidence_breaks_a_tie_the_gap_cannot(monkeypatch):
    att, full = _attribution(FakeMatched(TRIAL_48), GAPS, COST, monkeypatch)
    # of D = 81.7 the drift's term removes 81.7 - 5.6^2 - 3.1^2 = 40.7, the offset's 81.4
    d0 = att.matched.discrepancy([OFFSET, DRIFT, STEP])
    removed = {n: d0 - att.matched.discrepancy([OFFSET, DRIFT, STEP], (n,)) for n in (OFFSET, DRIFT)}
    assert removed[DRIFT] < TIE_FRACTION * removed[OFFSET]
    assert att._simplest_equivalent([OFFSET, DRIFT], full)[0] == OFFSET


def test_without_matched_evidence_occam_decides(monkeypatch):
    att, full = _attribution(None, GAPS, COST, monkeypatch)
    assert att._simplest_equivalent([OFFSET, DRIFT], full)[0] == DRIFT          # no matched tests
    att, full = _attribution(FakeMatched({}), GAPS, COST, monkeypatch)
    assert att._simplest_equivalent([OFFSET, DRIFT], full)[0] == DRIFT          # none fired


def test_candidates_the_matched_evidence_cannot_rank_either_stay_tied(monkeypatch):
    # the drift explains the offset's evidence away as well as the offset explains the drift's
    t = dict(TRIAL_48)
    t[(OFFSET, (DRIFT,))], t[(STEP, (DRIFT,))] = 0.6, 0.4
    att, full = _attribution(FakeMatched(t), GAPS, COST, monkeypatch)
    assert att._simplest_equivalent([OFFSET, DRIFT], full)[0] == DRIFT


def test_a_candidate_without_a_matched_test_is_not_dropped(monkeypatch):
    # a clock effect has no matched test: the evidence says nothing about it
    gaps, cost = {DRIFT: 0.972, "timestamp_jitter": 0.96}, {DRIFT: 3.0, "timestamp_jitter": 1.0}
    att, full = _attribution(FakeMatched(TRIAL_48), gaps, cost, monkeypatch)
    assert att._matched_equivalent(list(gaps)) == list(gaps)
    assert att._simplest_equivalent(list(gaps), full)[0] == "timestamp_jitter"


def test_given_a_selected_effect_the_evidence_left_decides(monkeypatch):
    # after a nonlinearity was selected, only the evidence that still fires given it counts
    t = {(k, tuple(sorted(g + ("scale_nonlinearity",)))): v for (k, g), v in TRIAL_48.items()}
    att, full = _attribution(FakeMatched(t), GAPS, COST, monkeypatch)
    assert att._simplest_equivalent([OFFSET, DRIFT], full, ("scale_nonlinearity",))[0] == OFFSET
    # a selected effect the tests cannot condition on (a noise model): nothing changes
    assert att._simplest_equivalent([OFFSET, DRIFT], full, ("colored_noise",))[0] == DRIFT


def test_a_gap_that_ranks_them_is_not_overruled(monkeypatch):
    # the drift closes much less of the gap: the bootstrap ranks it, whatever the tests say
    att, full = _attribution(FakeMatched(TRIAL_48), {OFFSET: 0.947, DRIFT: 1.15}, COST, monkeypatch,
                             boot_spread=0.01)
    assert att._simplest_equivalent([OFFSET, DRIFT], full)[0] == OFFSET
    t = {(DRIFT, ()): 6.27, (OFFSET, ()): 4.04, (OFFSET, (DRIFT,)): 0.5, (DRIFT, (OFFSET,)): 5.6}
    att, full = _attribution(FakeMatched(t), {OFFSET: 0.947, DRIFT: 1.15}, COST, monkeypatch, boot_spread=0.01)
    assert att._simplest_equivalent([OFFSET, DRIFT], full)[0] == OFFSET


@pytest.mark.slow
def test_the_thermal_offset_trial_is_named():
    """End to end on the trial itself, regenerated (about 30 s)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import blind_benchmark
    import blind_indep

    from mkc_stream.diagnose import diagnose

    rec, label = blind_indep.make_indep_trial("single", OFFSET, 400060, blind_benchmark)
    assert label["magnitude"]["value"] == pytest.approx(26.30, abs=0.01)
    d = diagnose(rec, profile="fast", seed=0)
    assert d.selected[:1] == [OFFSET] and d.verdict == "explained", (d.verdict, d.selected)
    assert DRIFT in d.ambiguous_with
