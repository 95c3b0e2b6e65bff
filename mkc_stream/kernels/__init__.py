"""Numba kernels: plain functions over fixed-size arrays, one-to-one with the C port.

Status codes returned by kernels (the C port uses the same numbers):
"""
OK = 0
NOT_CONVERGED = 1   # iteration cap reached; the result is the last iterate
SINGULAR = 2        # normal equations not positive definite (rank deficient or all weights ~0)
NONFINITE = 3       # a NaN/inf appeared; the previous estimate was kept
BAD_INPUT = 4       # inputs outside the domain (non-positive sigma or d, empty data)

STATUS_TEXT = {
    OK: "ok",
    NOT_CONVERGED: "iteration cap reached",
    SINGULAR: "normal equations singular",
    NONFINITE: "non-finite value",
    BAD_INPUT: "bad input",
}
