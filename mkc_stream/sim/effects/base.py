"""The shape of an effect in the library: named parameters with units, a forward model, the
signals it needs, a test of whether a recording can reveal it, and its diagnosis form.

Why this shape: the simulator and the diagnoser must agree on what an effect *is*, so both
read the one declaration. The simulator only needs ``forward``; the diagnoser needs to know,
before fitting anything, whether the recording holds the excitation or aux signal the effect
needs (``testable``), so it can say "not testable" instead of "absent", and how to fit it
(``form``: a :class:`~.form.MeanForm` or :class:`~.form.EstimatedForm`).

Units inside the simulator: uT, s, degC, A, throttle 0..1, rad. Parameters are given in the
natural unit each one names (nT/degC, %/degC, uT/h, ms ...) and converted in ``forward``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

#: Order in which the simulator applies effects (see mkc_stream.sim.sensor.simulate).
STAGES = ("field", "offset", "sensor", "noise", "range", "clock")


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    low: float           # realistic range (of the magnitude when the parameter is a signed component)
    high: float
    typical: float       # default value used when the user does not give one
    doc: str = ""


@dataclass
class SimContext:
    """What an effect's forward model may read and change while a recording is simulated.

    ``B`` (N, 3) true field at the sensor, sensor frame, uT (the field stage may change it);
    ``m`` (N, 3) the raw magnetometer under construction, uT; ``t`` true sample times (s);
    ``t_out`` reported timestamps (clock effects change these); ``keep`` samples that survive
    (sample drops clear entries); ``aux`` the aux signals; ``b``, ``S``, ``F`` the platform's
    hard iron, soft-iron correction and field strength; ``field_at(t)`` the true sensor-frame field
    at arbitrary times (for delays).
    """

    t: np.ndarray
    B: np.ndarray
    m: np.ndarray
    aux: dict
    b: np.ndarray
    S: np.ndarray
    F: float
    rng: np.random.Generator
    t_out: np.ndarray
    keep: np.ndarray
    field_at: Callable[[np.ndarray], np.ndarray] | None = None
    truth: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])


@dataclass
class Evidence:
    """What a recording offers for revealing effects (built by the diagnoser)."""

    n: int
    duration: float                     # s
    rate: float                         # Hz (median)
    aux_span: dict                      # usable aux column -> robust span (p97.5 - p2.5), its unit
    has_acc: bool
    has_gyro: bool
    coverage: float                     # fraction of equal-area direction cells visited
    rotation_rate: float                # 90th percentile angular rate, rad/s
    timestamps_real: bool               # False when t was made from the sample index


@dataclass(frozen=True)
class Effect:
    name: str
    family: str
    stage: str
    params: tuple
    needs: tuple                        # aux columns (or "acc") the effect needs to be revealed
    forward: Callable
    testable: Callable                  # (Evidence) -> (bool, reason)
    form: object                        # how the diagnoser fits it (MeanForm or EstimatedForm)
    doc: str = ""

    @property
    def kind(self) -> str:
        """How the diagnoser fits it (its form's kind): "mean", "noise", "clock" or "mask"."""
        return self.form.kind

    def defaults(self) -> dict:
        return {p.name: p.typical for p in self.params}

    def resolve(self, given: dict | None) -> dict:
        """Defaults overridden by ``given``; unknown names raise ValueError."""
        out = self.defaults()
        for k, v in (given or {}).items():
            if k not in out:
                raise ValueError(f"effect {self.name!r} has no parameter {k!r}; "
                                 f"it has {', '.join(out)}")
            out[k] = float(v)
        return out

    def apply(self, ctx: SimContext, given: dict | None = None) -> None:
        self.forward(ctx, **self.resolve(given))


# ---------------------------------------------------------------------------------------------
# helpers shared by several effect modules
# ---------------------------------------------------------------------------------------------

def aux_or_raise(ctx: SimContext, name: str, effect: str) -> np.ndarray:
    if name not in ctx.aux:
        raise ValueError(f"effect {effect!r} needs the aux signal {name!r}; the trajectory has "
                         f"{', '.join(ctx.aux) or 'none'}")
    return np.nan_to_num(np.asarray(ctx.aux[name], dtype=np.float64), nan=0.0)


def first_order_lag(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    """y' = (x - y) / tau on possibly irregular times (exact for x held between samples).

    tau <= 0 returns x. Why exact discretisation: thermal lags of minutes on 10-100 Hz data make
    a forward-Euler step fine, but gaps and drops make dt irregular, and this form is stable for
    any dt.
    """
    x = np.asarray(x, dtype=np.float64)
    if tau <= 0 or x.size == 0:
        return x.copy()
    from ._lag import lag_filter

    return lag_filter(np.asarray(t, dtype=np.float64), x, float(tau))


def span_ok(ev: Evidence, name: str, minimum: float, unit: str) -> tuple[bool, str]:
    span = ev.aux_span.get(name)
    if span is None:
        return False, f"the recording has no usable {name!r} column"
    if span < minimum:
        return False, f"{name!r} varies by only {span:.3g} {unit} (needs >= {minimum:g} {unit})"
    return True, f"{name!r} varies by {span:.3g} {unit}"


def coverage_ok(ev: Evidence, minimum: float = 0.5) -> tuple[bool, str]:
    if ev.coverage < minimum:
        return False, f"orientations cover {ev.coverage:.0%} of the sphere (needs >= {minimum:.0%})"
    return True, f"orientations cover {ev.coverage:.0%} of the sphere"


def vec(*c) -> np.ndarray:
    return np.array(c, dtype=np.float64)
