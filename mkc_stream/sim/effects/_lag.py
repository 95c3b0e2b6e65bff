"""The one loop the simulator and the diagnoser need that NumPy cannot vectorise: a first-order lag."""
import math

from ..._numba import kernel


@kernel
def lag_filter(t, x, tau):
    """y_k = y_{k-1} + (1 - exp(-dt/tau)) (x_k - y_{k-1}), y_0 = x_0 (starts in equilibrium)."""
    n = x.shape[0]
    y = x.copy()
    for k in range(1, n):
        a = 1.0 - math.exp(-max(t[k] - t[k - 1], 0.0) / tau)
        y[k] = y[k - 1] + a * (x[k] - y[k - 1])
    return y
