"""Normaliser of the truncated MKC-induced pdf, eq. (17) and the E-step of Algorithm 2.

With u = e/d and A = a/d the truncated pdf on [-a, a] is

    p(e) = exp(-sigma^2 (1 - exp(-e^2 / (2 d^2 sigma^2)))) / (d Z(sigma, A)),
    Z(sigma, A) = int_{-A}^{A} f(u) du,  f(u) = exp(-sigma^2 (1 - h(u))),  h(u) = exp(-u^2 / (2 sigma^2)).

(the paper's c_i is 1/Z; its "log(c_i - d_i)" in (29)-(31) is log(c_i / d_i)).

f never decays below its floor exp(-sigma^2), so naive adaptive quadrature over [-A, A] misses the
narrow head when A is large and can return 0 (log Z = -inf). We split off the floor exactly:

    Z = 2 [ A exp(-sigma^2) + int_0^{min(A, u_c)} g(u) du ],   g = f - exp(-sigma^2) = exp(-sigma^2) expm1(sigma^2 h),

and g is evaluated as f * (-expm1(-sigma^2 h)) so that neither factor overflows; f = exp(-sigma^2 (1 - h))
takes 1 - h from h = exp(-q), q = u^2 / (2 sigma^2) (exact by Sterbenz for h >= 1/2), or from its
series for q < 1e-3 where 1 - h would cancel: three transcendental calls per node, not four. g decreases
monotonically; u_c is where g falls below TAU (solved in closed form), so the rest of the
integral is below the float64 resolution of Z. The remaining integral is composite
Gauss-Legendre (10 nodes, quadrature.py) on panels sized to the local scale of g (1 near the Gaussian head, sigma in the
Gaussian-like tail), about 6-15 panels for any sigma in [0.05, 1e3]: a fixed, bounded cost,
which is what both an optimiser loop and the C port need.

Derivatives (used by the E-step optimiser), from the same nodes:
    dZ/dA     = 2 f(A)
    dZ/dsigma = 2 [ -2 sigma A exp(-sigma^2) + int_0^{u_c} (2 sigma (f h - g) + f h u^2 / sigma) du ]
"""
import math

from .._numba import kernel
from .quadrature import GL_NODES, GL_WEIGHTS

TAU = 1e-21          # g below this is invisible next to Z >= ~1.2 min(A, 1)
LOG_TAU = math.log(TAU)


@kernel
def cut_point(sigma):
    """u_c with g(u_c) = TAU: sigma^2 h = log1p(TAU exp(sigma^2)), computed without overflow."""
    s2 = sigma * sigma
    x = s2 + LOG_TAU                   # log(TAU exp(sigma^2))
    if x > 30.0:
        L = x + math.log1p(math.exp(-x))
    else:
        L = math.log1p(math.exp(x))
    h_c = L / s2
    if h_c >= 1.0:
        return 0.0
    return sigma * math.sqrt(-2.0 * math.log(h_c))


@kernel
def _panel_width(u, sigma):
    # Head (|u| < 3 max(1, sigma)): f ~ exp(-u^2/2) for big sigma, width-sigma bump for small
    # sigma. Tail: g ~ exp(-u^2/(2 sigma^2)), whose log changes by u w / sigma^2 over a panel.
    if u < 3.0 * max(1.0, sigma):
        return 1.5 * min(1.0, sigma)
    return min(2.0 * sigma, 10.0 * sigma * sigma / u)


@kernel
def omh_h(q):
    """(1 - h, h) with h = e^-q from at most one exp; series for small q, so 1 - h does not cancel.

    omh = q - q^2/2 + q^3/6 - q^4/24 + q^5/120 for q < 1e-3 (the next term is below 2e-18 of omh).
    f = exp(-sigma^2 omh) needs omh to a few ulps *relative*: its exponent can be O(1) there.
    """
    if q < 1e-3:
        omh = q * (1.0 - q * (0.5 - q * (1.0 / 6.0 - q * (1.0 / 24.0 - q * (1.0 / 120.0)))))
        return omh, 1.0 - omh
    h = math.exp(-q)
    return 1.0 - h, h


@kernel
def log_normaliser_grad(sigma, A):
    """Return (log Z, d log Z / d sigma, d log Z / d A) for sigma > 0, A > 0."""
    s2 = sigma * sigma
    floor = math.exp(-s2)
    uc = min(A, cut_point(sigma))
    Ig = 0.0
    Ids = 0.0
    u = 0.0
    nq = GL_NODES.shape[0]
    while u < uc:
        w = _panel_width(u, sigma)
        ub = min(u + w, uc)
        span = ub - u
        for j in range(nq):
            x = u + span * GL_NODES[j]
            q = x * x / (2.0 * s2)
            omh, h = omh_h(q)
            f = math.exp(-s2 * omh)                # f = exp(-sigma^2 (1 - h))
            g = f * (-math.expm1(-s2 * h))         # g = f - exp(-sigma^2), without cancellation
            wj = span * GL_WEIGHTS[j]
            Ig += wj * g
            Ids += wj * (2.0 * sigma * (f * h - g) + f * h * x * x / sigma)
        u = ub
    Z = 2.0 * (A * floor + Ig)
    dZ_ds = 2.0 * (-2.0 * sigma * A * floor + Ids)
    fA = math.exp(-s2 * (-math.expm1(-A * A / (2.0 * s2))))
    dZ_dA = 2.0 * fA
    return math.log(Z), dZ_ds / Z, dZ_dA / Z


@kernel
def log_normaliser(sigma, A):
    return log_normaliser_grad(sigma, A)[0]
