"""Gauss-Legendre nodes used by the normaliser quadrature (generated once, shared with C)."""
import numpy as np

GL_ORDER = 16
_x, _w = np.polynomial.legendre.leggauss(GL_ORDER)
# Map from [-1, 1] to [0, 1]: the kernels integrate panel by panel.
GL_NODES = np.ascontiguousarray(0.5 * (_x + 1.0))
GL_WEIGHTS = np.ascontiguousarray(0.5 * _w)
