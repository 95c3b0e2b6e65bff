"""One decorator policy for every jitted kernel.

cache=True so a second process starts fast; nogil so callers may thread; never fastmath,
because kernels are cross-checked bit-for-bit-ish against the C port and against NumPy.
"""
import numba

def kernel(fn=None, **overrides):
    opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
    opts.update(overrides)
    if fn is None:
        return lambda f: numba.njit(**opts)(f)
    return numba.njit(**opts)(fn)
