"""The field itself changes with position: a sensor moved through a gradient (a motion-capture
volume over a reinforced floor, a bench near steel) sees a field strength that follows where it
is, which a single field strength F cannot represent.

* field_gradient: |B| -> |B| + g . (p - p_median), with p the recording's local position
  (columns px, py, pz, m, docs/spec/recording.md) and g the gradient of the field strength along
  those axes, in nT/m (10-2000 nT/m indoors near iron; outdoors the Earth's own gradient,
  ~0.02 nT/m, is far below anything a magnetometer resolves). The field's direction is kept:
  its change with position (the rest of the gradient tensor) would need the attitude in the
  world frame, which a trajectory does not carry, and the diagnosis reads the field strength.

Diagnosis: linear in g. With m = S^-1 F u + b, a change dF of the field strength moves the raw
reading by S^-1 u dF = (m - b) / F dF, so the form's columns are (m - b) / F (p_k - median p_k)
for k = x, y, z. Testable only when the recording has a position that spans at least
MIN_SPAN_M; otherwise it is dropped with that reason.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext, aux_or_raise, vec
from .form import MeanForm, vec_magnitude

#: the recording's local position columns (m), docs/spec/recording.md
POSITION = ("px", "py", "pz")
#: a position that moves less than this (m, the largest robust span of the three axes) cannot
#: separate a gradient from the calibration's field strength
MIN_SPAN_M = 0.2


def _position(aux):
    """(N, 3) position about its median (m)."""
    p = np.stack([np.asarray(aux[c], dtype=np.float64) for c in POSITION], axis=1)
    return p - np.median(p, axis=0)


def _gradient_forward(ctx: SimContext, gx, gy, gz):
    for c in POSITION:
        aux_or_raise(ctx, c, "field_gradient")
    p = np.nan_to_num(_position(ctx.aux))
    dF = p @ (vec(gx, gy, gz) * 1e-3)                          # nT/m * m -> uT
    norm = np.maximum(np.linalg.norm(ctx.B, axis=1, keepdims=True), 1e-12)
    ctx.B += ctx.B / norm * dF[:, None]


def _gradient_testable(ev):
    missing = [c for c in POSITION if c not in ev.aux_span]
    if missing:
        return False, f"the recording has no usable position ({', '.join(missing)} missing; columns px, py, pz in m)"
    span = max(ev.aux_span[c] for c in POSITION)
    if span < MIN_SPAN_M:
        return False, f"the position spans only {span:.3g} m (needs >= {MIN_SPAN_M:g} m)"
    return True, f"the position spans {span:.3g} m"


def _gradient_designs(env):
    """One design when the recording has a position; none (no estimate) otherwise."""
    return [{}] if all(c in env.frame.aux for c in POSITION) else []


def _gradient_G(env, d):
    p = _position(env.frame.aux)

    def g(frame, m, st):
        radial = (m - st.b) / float(st.F)                      # S^-1 u: d m / d F
        return radial[:, :, None] * p[:, None, :]
    return g


def _gradient_magnitude(env, d, th):
    out = vec_magnitude(env, th, 1.0, True, "/m")
    out["meaning"] = "gradient of the field strength along px, py, pz"
    return out


FIELD_GRADIENT = Effect(
    name="field_gradient", family="field", stage="field",
    params=(Param("gx", "nT/m", 10.0, 2000.0, 300.0, "d|B|/d px"),
            Param("gy", "nT/m", 10.0, 2000.0, -200.0, "d|B|/d py"),
            Param("gz", "nT/m", 10.0, 2000.0, 500.0, "d|B|/d pz")),
    needs=POSITION, forward=_gradient_forward, testable=_gradient_testable,
    form=MeanForm(_gradient_designs, _gradient_G, 3, _gradient_magnitude),
    doc="field strength changes with position: |B| + g . (p - median p)")

EFFECTS = (FIELD_GRADIENT,)
