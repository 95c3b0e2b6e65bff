"""The play operator: the building block of rate-independent hysteresis models (a
Prandtl-Ishlinskii model is a weighted sum of plays); a recursion NumPy cannot vectorise."""
import numpy as np

from ..._numba import kernel


@kernel
def play_operator(x, width):
    """Per column j: y_0 = x_0, y_k = min(max(y_{k-1}, x_k - width), x_k + width).

    The output follows its input only once the input has moved ``width`` away from it, so
    y - x = -width while the input rises steadily, +width while it falls, and turns over as the
    input travels 2 width after a reversal, however fast it travels (x (N, d) float64).
    """
    n, d = x.shape
    y = np.empty_like(x)
    for j in range(d):
        y[0, j] = x[0, j]
        for k in range(1, n):
            v = y[k - 1, j]
            lo = x[k, j] - width
            hi = x[k, j] + width
            if v < lo:
                v = lo
            elif v > hi:
                v = hi
            y[k, j] = v
    return y
