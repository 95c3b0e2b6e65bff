"""Gauss-Legendre nodes used by the normaliser quadrature (generated once, shared with C).

10 nodes per panel: at the normaliser's panel widths (<= 1.5 min(1, sigma) in the head, the tail's
log-slope bounded per panel) GL10 is at the rounding floor already. Measured against 40-digit
references over sigma in [0.05, 1e3], A in [0.3, 1e6]: log Z to 9e-15 (GL16: 5e-15, GL8: 2e-11)
and sigma d log Z / d sigma to 1e-13 for sigma <= 50 (GL16 the same; above, both are limited by
the cancellation in the integrand, ~4e-11 absolute, far below the E-step's gtol 1e-7).
"""
import numpy as np

GL_ORDER = 10
_x, _w = np.polynomial.legendre.leggauss(GL_ORDER)
# Map from [-1, 1] to [0, 1]: the kernels integrate panel by panel.
GL_NODES = np.ascontiguousarray(0.5 * (_x + 1.0))
GL_WEIGHTS = np.ascontiguousarray(0.5 * _w)
