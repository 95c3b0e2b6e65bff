"""The verdict, decided from the numbers printed beside it.

Rules (each reads only the figures returned in :class:`Basis`):

* ``no_gap``: neither the held-out gap index (above its alarm level) nor a matched test
  detected a gap.
* ``explained``: the held-out gap index with the selected effects is at or below the alarm
  level, the first selected effect alone closes at least ``FIRST_ALONE`` of the excess gap, and,
  when only matched tests detected the gap, no fired test fires any more given the selected
  effects *and* the selected effects lower the held-out residual (below). A shrink alone, however
  large, never makes "explained": a gap index still above the alarm is a gap.
* ``partially_explained``: the selected effects close at least ``PARTIAL`` of the gap (held-out
  gap index; on matched evidence, the matched shrink, and then only when the held-out residual
  is lowered too).
* ``unexplained``: otherwise.

Why the held-out residual for matched evidence: when only matched tests fired, the gap index is
at its null level and its changes are mostly noise; the matched tests' own shrink is in-sample.
Evidence that was searched for in the whole recording must also show on blocks the fit did not
see, so the held-out (cross-fitted) residual sum of squares, each sample capped at
``RSS_CAP_SIGMA`` noise sigmas so that bursts do not decide it, must be lower with the selected
effects than without them:

    drop = sum_i min((e0_i / sigma)^2, c^2) - sum_i min((e1_i / sigma)^2, c^2)

over the samples valid in both models (both channels, each in its own sigma).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from . import gap

PARTIAL = 0.3
FIRST_ALONE = 0.7               # several weak effects that together mimic a gap are not an explanation
RSS_CAP_SIGMA = 4.0


@dataclass
class Basis:
    """The figures a verdict was decided from (printed beside it and in the JSON)."""

    detected_by: str | None              # "gap index", "matched tests" or None
    gap_before: float                    # held-out gap index of the baseline
    gap_after: float                     # held-out gap index with the selected effects
    alarm: float                         # the gap index's alarm level
    shrink: float                        # of the excess gap (matched: of the fired tests' excess)
    first_alone: float                   # shrink of the first selected effect alone
    matched_closed: bool | None = None   # matched evidence: no fired test fires given the selected
    held_out_rss_drop: float | None = None   # matched evidence: held-out residual drop (above)
    held_out_gyro_drop: float | None = None  # matched evidence with latency: the gyroscope's timing residual
    rule: str = ""                       # the rule that decided, in words
    notes: list = field(default_factory=list)   # later downgrades (an aux signal still followed ...)

    def to_json(self) -> dict:
        """The fields as a dict (non-finite numbers are made null by the JSON writer)."""
        return asdict(self)


def held_out_rss_drop(ev_before, ev_after, sigma) -> float:
    """Capped, noise-weighted held-out residual sum of squares before minus after (see the
    module documentation); > 0 when the selected effects fit blocks they did not see better."""
    ok = ev_before.valid & ev_after.valid
    cap = RSS_CAP_SIGMA ** 2
    s = np.asarray(sigma, dtype=float)[None, : ok.shape[1]]
    r0 = np.minimum((ev_before.e / s) ** 2, cap)
    r1 = np.minimum((ev_after.e / s) ** 2, cap)
    return float(np.sum(np.where(ok, r0 - r1, 0.0)))


def decide(detected_by, g0, g1, thr, selected, first_alone, matched=None, rss_drop=None, gyro_drop=None):
    """(verdict, Basis).

    detected_by: "gap index", "matched tests" or None. g0, g1: held-out gap index before and
    after the selected effects; thr: its alarm level. first_alone: shrink of the first selected
    effect alone. matched: (shrink, closed) on the matched evidence (detected_by "matched
    tests"); rss_drop: the held-out residual drop of the selected effects (same case);
    gyro_drop: the held-out drop of the gyroscope's timing residual when a latency is selected
    (:func:`.gyro_timing.gyro_delay`; its second view), which also counts as lowered."""
    first_alone = float(first_alone) if first_alone is not None else float("nan")
    if not detected_by:
        b = Basis(None, g0, g1, thr, float("nan"), float("nan"),
                  rule=f"gap index {_f(g0)} <= alarm {_f(thr)} and no matched test fired")
        return "no_gap", b
    on_matched = detected_by == "matched tests"
    if on_matched:
        s, closed = matched if matched is not None else (0.0, False)
        s = float(s) if selected else 0.0
        b = Basis(detected_by, g0, g1, thr, s, first_alone, matched_closed=bool(closed),
                  held_out_rss_drop=None if rss_drop is None else float(rss_drop),
                  held_out_gyro_drop=None if gyro_drop is None else float(gyro_drop))
    else:
        s = gap.shrink(g0, g1) if selected else 0.0
        b = Basis(detected_by, g0, g1, thr, s, first_alone)
    if not selected:
        b.rule = "no effect of the library pays for itself"
        return "unexplained", b
    below = bool(np.isfinite(g1) and g1 <= thr)
    first_ok = bool(np.isfinite(first_alone) and first_alone >= FIRST_ALONE)
    lowered = True if not on_matched else any(x is not None and np.isfinite(x) and x > 0 for x in (rss_drop, gyro_drop))
    closed = True if not on_matched else bool(b.matched_closed)
    why = [f"gap index with the selected effects {_f(g1)} {'<=' if below else '>'} alarm {_f(thr)}",
           f"first effect alone closes {_f(first_alone, 2)} ({'>=' if first_ok else '<'} {FIRST_ALONE:g})"]
    if on_matched:
        why += [f"matched tests {'all quiet' if closed else 'still firing'} given the selected effects",
                f"held-out residual {'lowered' if lowered else 'not lowered'} by {_f(rss_drop)}"
                + ("" if gyro_drop is None else f" (gyroscope timing residual by {_f(gyro_drop)})")]
    if below and first_ok and closed and lowered:
        b.rule = "; ".join(why)
        return "explained", b
    if lowered and np.isfinite(s) and s >= PARTIAL:
        b.rule = "; ".join(why + [f"closes {_f(s, 2)} (>= {PARTIAL:g})"])
        return "partially_explained", b
    b.rule = "; ".join(why + [f"closes {_f(s, 2)}" + ("" if lowered else ", not confirmed on held-out blocks")])
    return "unexplained", b


def _f(x, nd=3):
    return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}g}"
