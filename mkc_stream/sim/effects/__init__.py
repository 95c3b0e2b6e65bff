"""The effect library: ``EFFECTS[name]`` for every effect the simulator can add and the diagnoser
can test.

One module per effect family (thermal, electrical, drift, nonlinear, alignment, noise, timing,
field_gradient).
Each effect is one :class:`~.base.Effect` declaration in its family's module, holding both its
forward model (the simulator's) and its diagnosis form (the diagnoser's, :mod:`.form`); the
diagnoser indexes the forms from here. To add an effect: write its forward model and its form in
its family's module, declare the Effect there and list it in that module's ``EFFECTS``; a new
family module is also listed in FAMILIES below. Names follow docs/spec/machine-output.md.
"""
from __future__ import annotations

from . import alignment, drift, electrical, field_gradient, noise, nonlinear, thermal, timing
from .base import STAGES, Effect, Evidence, Param, SimContext

#: the family modules, in the library's order
FAMILIES = (thermal, electrical, drift, nonlinear, alignment, noise, timing, field_gradient)

EFFECTS: dict[str, Effect] = {e.name: e for module in FAMILIES for e in module.EFFECTS}

__all__ = ["EFFECTS", "FAMILIES", "STAGES", "Effect", "Evidence", "Param", "SimContext", "parse_effect"]


def parse_effect(text: str) -> tuple[str, dict]:
    """``"NAME:param=value,param=value"`` (or ``NAME`` alone) -> (name, {param: float})."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; the library has {', '.join(sorted(EFFECTS))}")
    params = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"effect parameter {item!r} is not of the form name=value")
        try:
            params[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"effect parameter {key.strip()!r} of {name}: {value!r} is not a number") from None
    EFFECTS[name].resolve(params)      # unknown parameter names raise here
    return name, params
