"""Which effect closes the gap, and by how much, on held-out blocks.

All scores are cross-fitted (:meth:`Engine.evaluate`): every block is scored by a fit that did
not see it.

1. Screen: every testable effect of the library is added alone to the baseline (mean effects
   fitted, stochastic/clock/mask effects estimated and added to the replicas) and scored with
   fewer replicas.
2. Select greedily: the best few candidates are re-scored with all replicas. Among
   deterministic candidates that the bootstrap cannot rank (and that close at least
   ``TIE_FRACTION`` of the best one's step), those whose term removes less than
   ``TIE_FRACTION`` of the fired matched evidence the best of them removes are not tied
   (:meth:`Attribution._matched_equivalent`, decision 0029); of the rest the simplest wins
   (fewest parameters and grid settings). The choice is kept if it pays for its parameters:
   it closes at least ``MIN_STEP`` of the remaining excess gap and lowers the gap with
   ``PAY_CONFIDENCE`` in a block bootstrap (real recording and replicas resampled alike). The
   next round adds each remaining effect to the kept ones (refitted jointly), until the gap is
   at its null level, nothing pays, or ``MAX_EFFECTS`` are kept.
   A stochastic effect that could mimic any slow deterministic one (random walk, coloured noise)
   pays the log of how much it widens the replicas (Dawid-Sebastiani), counts only when it closes
   the gap to its null level (or ``CATCH_ALL_CLOSE`` of it, or full closure is inside its shrink's
   bootstrap interval), beats a deterministic effect only
   when it closes ``STOCHASTIC_MARGIN`` more, significantly, and is considered in the first round
   only (after a deterministic effect, what is left is reported, not mopped up). It is
   implausible when the magnetometer lags the gyroscope (``LAG_ALPHA``): a noise independent of
   the motion cannot make it lag.
3. Ambiguity: an effect whose gap is not significantly above the first selected one's (paired
   bootstrap), or is itself at the null level, is reported as indistinguishable
   (``ambiguous_with``); cross_axis and misalignment have the same observable and are always
   ambiguous with each other.
4. Shrink = (G0 - G) / (G0 - 1) with a bootstrap interval; magnitudes in natural units with a
   bootstrap over the first fold's training blocks. For effects left out, the shrink they would
   add on top of the selected ones is ``shrink_given_selected``.
5. When the gap index is at its null level but a matched test of a mean effect fired
   (:mod:`.matched`), steps 2-4 are made on the matched evidence instead
   (:meth:`Attribution._run_matched`): the shrink is the fraction of the fired tests' excess
   an effect removes, ambiguity is "explains the first one's evidence away", and the selected
   magnitudes are refitted on all blocks.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from ..sim.effects import EFFECTS
from . import gap
from .catch_all import CATCH_ALL_CLOSE, LAG_ALPHA, SLOW_OFFSETS, CatchAllRules  # noqa: F401  (re-exported)
from .engine import CATCH_ALL, Candidate, Engine, Evaluation
from .forms import FORMS, MeanForm, implausible
from .matched import NULL_LEVEL
from .model import block_normals, bootstrap_theta, fit_model

MIN_STEP = 0.1
MAX_EFFECTS = 3
N_VERIFY = 3
PAY_CONFIDENCE = 0.9            # bootstrap confidence that an added effect lowers the gap
TIE_FRACTION = 0.9              # candidates closing at least this fraction of the best one's step may tie
STOCHASTIC_MARGIN = 0.15        # a catch-all stochastic effect must close this much more than the best
                                # deterministic one


@dataclass
class EffectResult:
    name: str
    testable: bool
    reason: str
    selected: bool = False
    status: str = "not testable"
    shrink: float | None = None
    shrink_ci: list | None = None
    gap: float | None = None
    magnitude: dict | None = None
    magnitude_ci: dict | None = None
    evaluation: Evaluation | None = field(default=None, repr=False)
    verified: bool = False
    shrink_given_selected: float | None = None
    why_implausible: str | None = None      # the screen's reason, also appended to ``reason``


def _resample(rng, blocks, B, n):
    out = np.zeros((n, B))
    for i in range(n):
        pick = rng.choice(blocks, size=blocks.size, replace=True)
        out[i] = np.bincount(pick, minlength=B)
    return out


class Attribution(CatchAllRules):
    def __init__(self, eng: Engine, ev0: Evaluation, thr: float, library, n_boot=100, seed=0, screen_R=20, log=None,
                 matched=None):
        self.eng, self.ev0, self.thr = eng, ev0, thr
        self.matched = matched      # MatchedTests of the mean effects (None: the gap index only)
        self.matched_summary = None
        self.library = list(library)
        self.rng = np.random.default_rng(seed + 7)
        self.boot = _resample(self.rng, np.arange(eng.frame.n_blocks), eng.frame.n_blocks, n_boot)
        self.screen_R = min(screen_R, eng.R)
        self.log = log or (lambda s: None)
        self._boot_cache = {}
        self.bad = {}               # effects whose fit in the last screen is outside the physical range

    # -- helpers ------------------------------------------------------------------------------
    def gap_R(self, ev: Evaluation, R):
        return ev.G if ev.rep_values.shape[0] == R else self.eng.gap_of(ev, R)

    def boot_gaps(self, ev: Evaluation):
        key = id(ev)
        if key not in self._boot_cache:
            self._boot_cache[key] = (ev, self.eng.boot_gaps(ev, self.boot))
        return self._boot_cache[key][1]

    def shrink_ci(self, ev_ref, ev):
        """90% bootstrap interval of the shrink; the excess gap it is a fraction of is held at
        its estimate (resamples with almost no excess would otherwise divide by ~0)."""
        g0, g1 = self.boot_gaps(ev_ref), self.boot_gaps(ev)
        ex = ev_ref.G - 1.0
        if not ex > 0:
            return None
        s = (g0 - g1) / ex
        s = s[np.isfinite(s)]
        if s.size < 10:
            return None
        return centred_interval(gap.shrink(ev_ref.G, ev.G), s)

    # -- screening ----------------------------------------------------------------------------
    def screen(self, ref: Evaluation, names, R):
        g_ref = self.gap_R(ref, R)
        out = {}
        for name in names:
            cand = self.eng.extend(ref, name)
            if cand is None:
                out[name] = (None, None, 0.0)
                continue
            ev = self.eng.evaluate(cand, R=R)
            out[name] = (cand, ev, gap.shrink(g_ref, ev.G))
            why = (implausible(name, self.term_magnitude(ev, name)) or self.eng.limit_reason(cand, name)
                   or self.lag_reason(name))
            if why:
                self.bad[name] = why
            else:
                self.bad.pop(name, None)
            self.log(f"    {name:24s} gap {ev.G:8.3f}  shrink {out[name][2]:+.2f}{'  (implausible)' if why else ''}")
        return out

    def term_magnitude(self, ev, name):
        """Magnitude of a mean effect as fitted in ev (None for estimated effects)."""
        idx = [i for i, t in enumerate(ev.cand.terms) if t.name == name]
        if not idx:
            return None
        t = ev.cand.terms[idx[0]]
        return FORMS[name].magnitude(self.eng.env, t.design, ev.fit.theta[idx[0]])

    # -- selection ----------------------------------------------------------------------------
    def run(self, detected: bool, by_matched: bool = False):
        """by_matched: the gap index is at its null level and only matched tests fired: the
        attribution is then made on the matched evidence (:meth:`_run_matched`)."""
        eng, ev0 = self.eng, self.ev0
        results = {}
        testable = []
        for name in self.library:
            ok, why = effect_testable(eng.base, name)
            results[name] = EffectResult(name, bool(ok), why, status="not testable" if not ok else "not selected")
            if ok:
                testable.append(name)
        self.log(f"  screening {len(testable)} testable effects ({self.screen_R} replicas each)")
        screened = self.screen(ev0, testable, self.screen_R)
        first_bad = dict(self.bad)
        for name, why in first_bad.items():
            results[name].status = "implausible"
            results[name].reason += "; " + why
            results[name].why_implausible = why
        singles = {}
        for name in testable:
            cand, ev_s, s = screened[name]
            r = results[name]
            if ev_s is None:
                r.shrink, r.status = 0.0, "no estimate"
                r.reason += "; the data give no estimate of it"
                continue
            r.shrink, r.gap, r.evaluation = s, ev_s.G, ev_s
            singles[name] = cand

        selected, current = [], ev0
        if detected and by_matched:
            selected, current, ambiguous = self._run_matched(results, singles, first_bad)
            for n in selected:
                results[n].selected, results[n].status = True, "selected"
            for n in ambiguous:
                results[n].status = "ambiguous"
            self._magnitudes(results, current, selected)
            self._whole_magnitudes(results, current, selected)
            return results, selected, ambiguous, current
        if detected:
            remaining = [n for n in testable if n in singles]
            scores = {n: results[n].shrink for n in remaining}
            rnd = 0
            while remaining and len(selected) < MAX_EFFECTS:
                best = self._round(rnd, current, remaining, scores, singles, results, tuple(selected))
                if best is None:
                    break
                name, ev_best = best
                step = gap.shrink(current.G, ev_best.G)
                gain = self.boot_gaps(current) - self.boot_gaps(ev_best)
                lo = float(np.percentile(gain, 100 * (1 - PAY_CONFIDENCE)))
                if not (np.isfinite(step) and step >= MIN_STEP and lo > 0):
                    self.log(f"  {name} does not pay (closes {step:.2f} of the remaining gap, bootstrap 5% {lo:.3g})")
                    break
                selected.append(name)
                current = ev_best
                remaining.remove(name)
                self.log(f"  selected {name}: gap {current.G:.3f}")
                if current.G <= self.thr or len(selected) >= MAX_EFFECTS:
                    break           # (a screen for a round that will not run costs ~10 s)
                rnd += 1
                # catch-alls compete in the first round only (see _round): not screened again
                rs = self.screen(current, [n for n in remaining if n not in CATCH_ALL], self.screen_R)
                scores = {n: rs[n][2] for n in rs}

        selected, current, replaced = self._one_catch_all_for_slow_offsets(selected, current, results)
        for n in selected:
            results[n].selected, results[n].status = True, "selected"
        ambiguous = self._ambiguity(selected, results, singles, first_bad) if selected else []
        ambiguous += [n for n in replaced if n not in ambiguous]
        for n in ambiguous:
            results[n].status = "ambiguous"
        if selected:
            self._conditional(results, current, selected)
        self._magnitudes(results, current, selected)
        return results, selected, ambiguous, current

    def _run_matched(self, results, singles, bad):
        """Attribution when only matched tests fired (the gap index is at its null level, so
        its changes are noise): everything is measured on the matched evidence.

        * shrink of an effect: the fraction of the fired tests' excess (sum of max(t, 0)^2 over
          its null level) that adding its term removes (conditional tests); noise, clock and
          mask effects do not change a mean pattern and get no shrink here;
        * first: the effect removing the most of it; among those removing at least
          TIE_FRACTION of the best one's, the one whose own test is the most significant;
        * ambiguous: a fired effect that explains the first one's evidence away (the first's
          test no longer fires given it): the data cannot tell them apart;
        * further effects: those whose test still fires given the selected ones (most
          significant first), up to MAX_EFFECTS.
        """
        mt = self.matched
        fired = mt.fired()
        ok = [n for n in fired if n in singles and n not in bad]
        shr = {n: mt.shrink(fired, (n,)) for n in mt.names}
        for name, r in results.items():
            if not r.testable or r.evaluation is None:
                continue
            src = name if name in shr else FORMS[name].alias_of
            r.shrink = shr.get(src, float("nan"))
            r.shrink_ci = None
        self.matched_summary = {"fired": fired, "level": mt.level, "tests": mt.summary()}
        self.log(f"  matched tests fired: {', '.join(fired)}; shrink " +
                 ", ".join(f"{n} {shr[n]:.2f}" for n in fired))
        if not ok:
            return [], self.ev0, []
        # the effect that explains the most of the fired evidence; among those the conditional
        # tests cannot rank (TIE_FRACTION of the best), the most significant test: its replicas
        # searched the same settings, so a form with many (a step's 63 times) pays for them
        best = max(shr[n] for n in ok)
        tied = [n for n in ok if shr[n] >= TIE_FRACTION * best]
        first = max(tied, key=lambda n: mt.result(n)["t"])
        # a form that holds a tied one as a special case is not the simpler explanation
        inner = [n for n in tied if n in getattr(FORMS[first], "contains", ())]
        if inner:
            first = max(inner, key=lambda n: mt.result(n)["t"])
        ambiguous = [n for n in ok if n != first and mt.result(first, (n,))["p"] >= mt.level]
        for name in results:                       # same observable (cross_axis / misalignment)
            if name != first and results[name].testable and (FORMS[name].alias_of == first
                                                             or FORMS[first].alias_of == name):
                ambiguous.append(name)
        selected = [first]
        while len(selected) < MAX_EFFECTS:
            more = [n for n in mt.fired(given=tuple(selected), among=ok) if n not in ambiguous]
            if not more:
                break
            selected.append(min(more, key=lambda n: mt.result(n, tuple(selected))["p"]))
        cand = singles[first]
        for n in selected[1:]:
            cand = self.eng.extend(SimpleNamespace(cand=cand), n) or cand     # mean effects: a term
        final = self.eng.evaluate(cand)
        s_all = mt.shrink(fired, tuple(selected))
        closed = not mt.fired(given=tuple(selected), among=fired)
        self.matched_summary.update(shrink=s_all, closed=closed)
        d_sel = mt.discrepancy(fired, tuple(selected))
        ex = mt.discrepancy(fired) - len(fired) * NULL_LEVEL
        for name in mt.names:
            if name not in selected and results[name].evaluation is not None and ex > 0:
                g = tuple(sorted(set(selected) | {name}))
                results[name].shrink_given_selected = float((d_sel - mt.discrepancy(fired, g)) / ex)
        self.log(f"  selected {', '.join(selected)} on the matched evidence (closes {s_all:.2f}"
                 f"{', nothing left' if closed else ''}); ambiguous with {', '.join(ambiguous) or '-'}")
        return selected, final, ambiguous

    def _round(self, rnd, current, remaining, scores, singles, results, given=()):
        """Best candidate of a selection round, re-scored with all replicas.

        Deterministic effects first; a catch-all stochastic effect (random walk, coloured noise)
        is chosen only when it is clearly better than the best deterministic one (bootstrap),
        because it can mimic any slow deterministic effect by widening its replicas.
        """
        def ok(n):
            return np.isfinite(scores.get(n, np.nan)) and scores[n] > 0 and n not in self.bad

        self._round_ref = current
        det = sorted([n for n in remaining if n not in CATCH_ALL and ok(n)], key=lambda n: -scores[n])[:N_VERIFY]
        # a catch-all is an explanation of the gap, not a mop for what a wrong-form effect leaves:
        # it competes in the first round only
        # both catch-alls are re-scored: a random walk and a slow coloured noise are the same
        # process over a recording much shorter than the noise's correlation time, and the
        # screen's few replicas cannot rank them (Occam decides below)
        sto = sorted([n for n in remaining if n in CATCH_ALL and ok(n)], key=lambda n: -scores[n])
        sto = sto if rnd == 0 else []
        full = {}
        for n in det + sto:
            cand = singles[n] if rnd == 0 else self.eng.extend(current, n)
            if cand is None:
                continue
            full[n] = self.eng.evaluate(cand)
            self.log(f"  round {rnd + 1}: {n:24s} gap {full[n].G:.3f} (all replicas)")
            if rnd == 0:
                self._set_single(results[n], full[n])
        dets = self._simplest_equivalent([n for n in full if n not in CATCH_ALL], full, given)
        # a catch-all stochastic effect is an explanation only when it makes the replicas
        # indistinguishable from the recording (gap at its null level, nearly all of it closed,
        # or full closure within its interval); closing part of a gap by widening the replicas
        # says nothing about its cause
        stos = [n for n in full if n in CATCH_ALL and self._closes_all(current, full[n], results[n])]
        best_det = dets[0] if dets else None
        best_sto = self._simplest_equivalent(stos, full)[0] if stos else None
        if best_sto == "colored_noise" and "bias_random_walk" in stos and self._walk_like(full[best_sto]):
            best_sto = "bias_random_walk"
        if best_det is None and best_sto is None:
            return None
        if best_det is None:
            return best_sto, full[best_sto]
        if best_sto is not None and full[best_sto].G < full[best_det].G:
            s_det, s_sto = gap.shrink(current.G, full[best_det].G), gap.shrink(current.G, full[best_sto].G)
            diff = self.boot_gaps(full[best_det]) - self.boot_gaps(full[best_sto])
            if s_sto >= s_det + STOCHASTIC_MARGIN and np.percentile(diff, 5) > 0:
                return best_sto, full[best_sto]
        return best_det, full[best_det]

    def _step(self, full, name):
        return gap.shrink(self._round_ref.G, full[name].G)

    def _simplest_equivalent(self, names, full, given=()):
        """Candidates ordered best first, where "best" is the simplest (fewest parameters and
        settings to choose from) among those whose gap is not significantly above the lowest
        one (paired bootstrap) and that explain as much of the fired matched evidence
        (:meth:`_matched_equivalent`): Occam between explanations the data cannot rank."""
        if len(names) < 2:
            return names
        lead = min(names, key=lambda n: full[n].G)
        gl = self.boot_gaps(full[lead])
        s_lead = self._step(full, lead)
        tied = [n for n in names if n == lead or (self._step(full, n) >= TIE_FRACTION * s_lead
                                                  and np.percentile(self.boot_gaps(full[n]) - gl, 5) <= 0)]
        if len(tied) > 1:
            tied = self._matched_equivalent(tied, given)
        pick = min(tied, key=lambda n: (complexity(n, full[n].cand, self.eng.env), full[n].G))
        return [pick] + sorted([n for n in names if n != pick], key=lambda n: full[n].G)

    def _matched_equivalent(self, names, given=()):
        """Of candidates the held-out gap cannot rank, those the matched tests cannot rank
        either: each removes at least TIE_FRACTION of the fired matched evidence the best of
        them removes (the same measure and fraction as :meth:`_run_matched`), given the effects
        already selected. The held-out gap is an omnibus over hundreds of statistics; a matched
        test reads one form's pattern directly (a thermal offset under a temperature ramp
        against a drift: the ramp's bends), so where it fired it can separate what the gap
        ties. Candidates without a matched test (noise, clock and mask effects) stay tied; with
        no fired evidence, or a selected effect the tests cannot condition on, nothing changes.

        removed(n) = (D(E | given) - D(E | given + n)) / (D(E | given) - NULL_LEVEL |E|),
        D the sum of max(t, 0)^2 over the tests E that fire given the selected effects."""
        mt = self.matched
        if mt is None:
            return names

        def test_of(n):
            return n if n in mt.names else FORMS[n].alias_of if FORMS[n].alias_of in mt.names else None

        cond = tuple(test_of(n) for n in given)
        if None in cond:
            return names
        evidence = mt.fired(given=cond)
        d_given = mt.discrepancy(evidence, cond)
        excess = d_given - NULL_LEVEL * len(evidence)
        if not evidence or not excess > 0:
            return names
        removed = {n: (d_given - mt.discrepancy(evidence, cond + (test_of(n),))) / excess
                   for n in names if test_of(n) is not None}
        best = max(removed.values(), default=0.0)
        if not best > 0:
            return names
        keep = [n for n in names if n not in removed or removed[n] >= TIE_FRACTION * best]
        dropped = [n for n in names if n not in keep]
        if dropped:
            self.log("  the matched evidence ranks what the gap ties: removed " +
                     ", ".join(f"{n} {removed[n]:.2f}" for n in names if n in removed) +
                     f"; not tied: {', '.join(dropped)}")
        return keep

    def _set_single(self, r, ev):
        r.shrink, r.gap, r.evaluation, r.verified = gap.shrink(self.ev0.G, ev.G), ev.G, ev, True
        r.shrink_ci = self.shrink_ci(self.ev0, ev)

    def _ambiguity(self, selected, results, singles, bad=()):
        """Effects the data cannot tell apart from the first selected one (a fit outside the
        physical range is no alternative explanation)."""
        first = selected[0]
        ra = results[first]
        ev_a = ra.evaluation
        out = []
        for name, r in results.items():
            if name == first or not r.testable or r.evaluation is None or name in selected or name in bad:
                continue
            if FORMS[name].alias_of == first or FORMS[first].alias_of == name:
                out.append(name)
                continue
            if not (r.shrink is not None and np.isfinite(r.shrink) and r.shrink > 0.5 * ra.shrink):
                continue
            if not r.verified:
                self._set_single(r, self.eng.evaluate(singles[name]))
            diff = self.boot_gaps(r.evaluation) - self.boot_gaps(ev_a)
            if r.gap <= self.thr or np.percentile(diff, 5) <= 0:
                out.append(name)
        return out

    def _conditional(self, results, final, selected):
        """For effects left out: how much more of the excess gap they would close on top of the
        selected ones (what a user adding them to the simulator would gain)."""
        g0 = self.ev0.G
        for name, r in results.items():
            if name in selected or r.evaluation is None:
                continue
            if not (r.shrink is not None and np.isfinite(r.shrink) and r.shrink > 0.2):
                r.shrink_given_selected = 0.0 if r.testable else None
                continue
            # (a coloured noise's refinement costs four scorings: not for a reported figure)
            cand = self.eng.extend(final, name, refine=False)
            if cand is None:
                r.shrink_given_selected = 0.0
                continue
            ev = self.eng.evaluate(cand, R=self.screen_R)
            r.shrink_given_selected = float((self.gap_R(final, self.screen_R) - ev.G) / max(g0 - 1.0, 1e-9))

    def _magnitudes(self, results, final: Evaluation, selected):
        eng = self.eng
        for name, r in results.items():
            if r.evaluation is None:
                continue
            ev = final if name in selected else r.evaluation
            cand = ev.cand
            if name in cand.estimated:
                p = cand.estimated[name]
                r.magnitude = FORMS[name].magnitude(eng.env, p)
                if r.verified or name in selected:
                    r.magnitude_ci = self._estimated_ci(name, ev)
                continue
            idx = [i for i, t in enumerate(cand.terms) if t.name == name]
            if not idx:
                continue
            i = idx[0]
            term = cand.terms[i]
            form = FORMS[name]
            r.magnitude = form.magnitude(eng.env, term.design, ev.fit.theta[i])
            if r.verified or name in selected:
                A_b, g_b = block_normals(ev.fit, eng.frame.block, eng.frame.n_blocks)
                train = np.flatnonzero(eng.train_mult > 0)
                vals = []
                for m in _resample(self.rng, train, eng.frame.n_blocks, 200):
                    th = bootstrap_theta(ev.fit, A_b, g_b, m)[i]
                    vals.append(form.magnitude(eng.env, term.design, th)["value"])
                r.magnitude_ci = {"value": centred_interval(r.magnitude["value"], np.array(vals)),
                                  "unit": r.magnitude.get("unit")}

    def _whole_magnitudes(self, results, final, selected):
        """Magnitudes of the selected mean effects refitted on all blocks (the held-out
        evaluation fits each fold on half of them): near the detection limit, where the matched
        tests work, half the data doubles the noise a magnitude's norm is biased up by. The
        interval keeps its bootstrap spread, moved to the new point."""
        eng = self.eng
        terms = final.cand.terms
        if not terms:
            return
        fit = fit_model(eng.frame, eng.base.fit.state, terms, final.valid, eng.base.sigma, iters=3)
        for i, t in enumerate(terms):
            r = results.get(t.name)
            if r is None or t.name not in selected:
                continue
            mag = FORMS[t.name].magnitude(eng.env, t.design, fit.theta[i])
            if r.magnitude_ci and r.magnitude and r.magnitude.get("value") is not None:
                shift = mag["value"] - r.magnitude["value"]
                r.magnitude_ci = {**r.magnitude_ci, "value": [v + shift for v in r.magnitude_ci["value"]]}
            r.magnitude = mag

    def _estimated_ci(self, name, ev):
        eng = self.eng
        form = FORMS[name]
        base_ev = self.ev0              # the estimate of the effect alone, from the baseline's residuals
        # the resamples use the form's first estimate only: when a coloured noise's refinement
        # won (Engine._refined), the interval is that spread around the refined point (a refined
        # resample costs four scorings; 40 of them would double a diagnosis)
        vals = []
        train = np.flatnonzero(eng.train_mult > 0)
        for m in _resample(self.rng, train, eng.frame.n_blocks, 40):
            try:
                p = form.estimate(eng.env, base_ev, m)
            except Exception:  # noqa: BLE001 - a resample can be degenerate
                p = None
            if p is not None:
                vals.append(form.magnitude(eng.env, p)["value"])
        if len(vals) < 10:
            return None
        point = form.magnitude(eng.env, ev.cand.estimated[name])
        return {"value": centred_interval(point["value"], np.array(vals)), "unit": point.get("unit")}


def centred_interval(point, boot, level=0.9):
    """Basic bootstrap interval around the point estimate: its spread from the resamples, its
    centre from the estimate (the resamples' own statistics need not be centred on it)."""
    lo, med, hi = np.percentile(boot, [50 * (1 - level), 50, 50 * (1 + level)])
    return [float(point + lo - med), float(point + hi - med)]


def complexity(name, cand, env) -> float:
    """Parameters of an effect in a candidate, plus log2 of the settings its grid chose from."""
    form = FORMS[name]
    if isinstance(form, MeanForm):
        term = next((t for t in cand.terms if t.name == name), None)
        n_opt = len(term.options) if term is not None and term.options else 1
        return form.k + np.log2(n_opt)
    p = cand.estimated.get(name, {})
    if name == "colored_noise":        # two parameters per Gauss-Markov component it actually has
        return 2.0 * sum(1 for s_, _ in p.get("components", ()) if s_ > 0)
    return float(len(p))


def effect_testable(base, name):
    """(testable, reason) of an effect on this baseline: the registry's test of the recording's
    excitation and aux signals, then what the baseline's calibration allows (:mod:`.scope`)."""
    if base.scope is None:
        return EFFECTS[name].testable(base.evidence)
    return base.scope.effect_testable(EFFECTS[name], base.evidence)


__all__ = ["Attribution", "EffectResult", "effect_testable", "Candidate", "MeanForm"]
