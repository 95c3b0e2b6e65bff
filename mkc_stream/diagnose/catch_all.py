"""When a catch-all noise model (random walk, coloured noise) may stand as the explanation.

A catch-all widens the replicas, so it can mimic any slow effect. These rules say when it counts
(:meth:`CatchAllRules._closes_all`), when it cannot be the cause (:meth:`CatchAllRules.lag_reason`),
which of the two a slow noise is (:meth:`CatchAllRules._walk_like`), and when it replaces several
slow offsets (:meth:`CatchAllRules._one_catch_all_for_slow_offsets`). They are methods of
:class:`.attribution.Attribution`, which holds what they read: the baseline evaluation ``ev0``,
the alarm level ``thr``, the implausible effects ``bad``, the paired bootstrap ``boot_gaps``, the
Occam ranking ``_simplest_equivalent``, the matched tests and the engine.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from . import gap
from .engine import CATCH_ALL

CATCH_ALL_CLOSE = 0.95          # a catch-all counts when it closes nearly all of the gap
LAG_ALPHA = 1e-3                # one-sided level of the gyroscope timing test above which a catch-all
                                # is implausible (see CatchAllRules.lag_reason)
#: slow hard-iron shapes: two or more of them selected together, where a catch-all alone closes
#: the gap, are a random walk's path cut into pieces (decision 0032)
SLOW_OFFSETS = ("hard_iron_drift", "hard_iron_step", "temperature_offset")


class CatchAllRules:
    """The catch-all rules of :class:`.attribution.Attribution` (a mixin: no state of its own)."""

    def lag_reason(self, name):
        """Why a catch-all cannot explain this recording, or None.

        A random walk or coloured noise in the hard iron is independent of the motion, so it
        cannot make the magnetometer's rotation lag the gyroscope's (:mod:`.gyro_timing`:
        r = dB/dt + w x B regressed on dw/dt x B). A hysteresis or a latency does. When the
        timing test reads the magnetometer late beyond chance (one-sided p < LAG_ALPHA), a
        catch-all that widens the replicas until the gap closes is hiding that lag.
        """
        g = getattr(self.matched, "gyro", None)
        if name not in CATCH_ALL or g is None or not g["t"] > 0:
            return None
        if float(stats.t.sf(g["t"], g["dof"])) >= LAG_ALPHA:
            return None
        return (f"the magnetometer lags the gyroscope by {g['delay_ms']:.2f} +- {g['se_ms']:.2f} ms "
                f"(t {g['t']:.1f}), which a noise independent of the motion cannot produce: not taken as "
                "the explanation (a hysteresis or a latency can lag)")

    def _closes_all(self, ref, ev, r):
        """A catch-all makes the replicas indistinguishable from the recording: its gap is at
        the null level, it closes ``CATCH_ALL_CLOSE`` of the excess, or full closure lies inside
        its shrink's 90% bootstrap interval (r.shrink_ci, set in the first round, the only one
        catch-alls compete in). A fixed fraction alone would be a bar the resampling noise of a
        short recording decides."""
        if ev.G <= self.thr or gap.shrink(ref.G, ev.G) >= CATCH_ALL_CLOSE:
            return True
        return r.shrink_ci is not None and r.shrink_ci[1] >= 1.0

    def _walk_like(self, ev):
        """A coloured noise whose components all have correlation times longer than the
        recording is a random walk over it: its increments grow linearly at every lag the
        recording holds (the variogram of the blocks' apparent hard iron bends by less than
        1 - e^-1 at the longest lag), so the one-parameter walk is the simpler equivalent."""
        comps = [c for c in ev.cand.estimated.get("colored_noise", {}).get("components", ()) if c[0] > 0]
        return bool(comps) and min(t for _, t in comps) >= self.eng.frame.duration

    def _one_catch_all_for_slow_offsets(self, selected, current, results):
        """(selected, evaluation, replaced): a selection made only of two or more slow offsets
        (SLOW_OFFSETS), where a catch-all alone closes the gap (:meth:`_closes_all`) and the
        paired bootstrap does not put its gap above theirs, becomes that catch-all; the offsets
        it replaces are returned to be listed as ambiguous.

        Why: a random walk's path over a recording is a sum of slow shapes. One offset form
        follows 0.3-0.8 of it (tools/blind_shapes.py), so the rounds take a drift, then a step or
        a thermal offset for the rest: six to nine coefficients and a step time where the walk
        has one intensity. Each round adds a shape the bootstrap says pays, and a catch-all
        competes in the first round only, so the rounds alone never compare the whole set with
        it. A single slow offset is left alone: there the catch-all must still beat it by
        STOCHASTIC_MARGIN (:meth:`_round`)."""
        if len(selected) < 2 or not all(n in SLOW_OFFSETS for n in selected):
            return selected, current, []
        ok = []
        for n in CATCH_ALL:
            r = results.get(n)
            if r is None or n in self.bad or r.evaluation is None or not r.verified:
                continue
            if not self._closes_all(self.ev0, r.evaluation, r):
                continue
            if np.percentile(self.boot_gaps(r.evaluation) - self.boot_gaps(current), 5) <= 0:
                ok.append(n)
        if not ok:
            return selected, current, []
        full = {n: results[n].evaluation for n in ok}
        best = self._simplest_equivalent(ok, full)[0]
        if best == "colored_noise" and "bias_random_walk" in ok and self._walk_like(full[best]):
            best = "bias_random_walk"
        self.log(f"  {best} alone explains what {', '.join(selected)} explain together: selected in their place")
        return [best], full[best], list(selected)
