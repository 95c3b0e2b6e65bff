"""JSON output values: the one place that turns results into strict-JSON-safe objects.

JSON has no NaN/inf: an unknown (non-finite) number is written as null (docs/spec/machine-output.md);
numpy scalars and arrays become plain Python numbers and lists, tuples become lists, dict keys
strings. Every writer of machine output (the CLI, Calibration.to_json, the diagnosis report, the
study tools) goes through :func:`jsonable`.
"""

from __future__ import annotations

import math


def jsonable(obj):
    """A JSON-safe copy of obj: non-finite floats -> None, numpy scalars/arrays -> Python numbers/lists,
    bools stay bools and integers stay integers, dict keys -> str, tuples -> lists; anything else unchanged."""
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):                                   # numpy.float64 too
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if hasattr(obj, "item") and hasattr(obj, "dtype"):          # numpy scalars and arrays (numpy is not imported here)
        return jsonable(obj.item() if getattr(obj, "ndim", 0) == 0 else obj.tolist())
    return obj


def finite_or_none(x):
    """A scalar as a float, or None when it is None or not finite (NaN/inf)."""
    return None if x is None else jsonable(float(x))
