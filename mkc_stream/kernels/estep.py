"""E-step: per-channel maximum likelihood of (sigma_i, d_i), eqs. (29)-(31), Algorithm 2.

Objective (per channel, divided by N so its scale does not depend on N), with the paper's
"log(c_i - d_i)" read as log(c_i / d_i) = -log(d_i Z):

    F(sigma, d) = log d + log Z(sigma, a/d) + (sigma^2 / N) sum_k (1 - exp(-e_k^2 / (2 d^2 sigma^2)))
                  - (pull / N) log sigma

minimised over z = (log sigma, log d) inside a box (so sigma can never collapse to 0 or d to a
spike) by a projected BFGS (the paper's Algorithm 2 uses BFGS) with Armijo backtracking, an
active-set rule at the bounds, analytic gradients, a bounded iteration count and a warm start.
A non-finite value is treated as a failed trial step, so NaN never enters the state.

The last term is ours, not the paper's (pull = 0 is its ML): a prior p(sigma) ~ sigma^pull, worth
`pull` nats per e-fold of sigma over the whole window. Once sigma exceeds the residuals' range the
induced pdf is Gaussian whatever sigma is, and the likelihood is flat to ~0.1 nat from sigma ~ 5
to 1000 (Section III-D); a capped, warm-started BFGS then stops wherever its gradient first falls
below gtol, so the stream's sigma wanders along the flat ridge and takes the calibration with it
(a 1e-7 change of the input moved a real recording's calibration by up to 2.8e-3). A pull of 0.05 nat per
e-fold sends that ridge to the Gaussian end (sigma_hi), where the weights are 1 and the fit is
plain least squares, and moves a real optimum (tens of nats deep once bursts are present) by
~pull / curvature, i.e. not visibly.
"""
import math

from .._numba import kernel
from . import OK, NOT_CONVERGED, NONFINITE, BAD_INPUT
from .normaliser import log_normaliser_grad


# A capped E-step (a stream's generalised EM step) may run FAR_EXTRA_ITER iterations beyond its cap
# while the projected gradient is above FAR_GTOL: after a burst enters a clean window the optimum
# jumps (sigma from the Gaussian regime ~1e2-1e3 down to ~2), and three iterations leave the stream
# tracking a stale kernel for several checkpoints. In steady state this costs nothing.
FAR_GTOL = 1e-2
FAR_EXTRA_ITER = 9


@kernel
def _omh_terms(q):
    """(1 - h, (1 - h) - q h, h) with h = e^-q, from one exp (the E-step's hot loop).

    Small q uses series, so neither 1 - h nor (1 - h) - q h = q^2/2 - q^3/3 + q^4/8 - ... cancels.
    """
    if q < 1e-3:
        omh = q * (1.0 - q * (0.5 - q * (1.0 / 6.0 - q * (1.0 / 24.0))))
        return omh, q * q * (0.5 - q * (1.0 / 3.0 - q * 0.125)), 1.0 - omh
    h = math.exp(-q)
    omh = 1.0 - h
    return omh, omh - q * h, h


@kernel
def estep_objective(ls, ld, e, n, a, pull):
    """F and its gradient in (log sigma, log d) for residuals e[:n] on the truncation [-a, a]."""
    sigma = math.exp(ls)
    d = math.exp(ld)
    s2 = sigma * sigma
    logZ, dZs, dZA = log_normaliser_grad(sigma, a / d)
    inv = 1.0 / (2.0 * d * d * s2)
    acc = 0.0
    acc_s = 0.0
    acc_d = 0.0
    for k in range(n):
        q = e[k] * e[k] * inv
        omh, omh_qh, h = _omh_terms(q)
        acc += omh
        # d/dsigma [sigma^2 (1-h)] = 2 sigma (1-h) - h e^2/(d^2 sigma) = (2 sigma)(1-h-qh)
        acc_s += omh_qh
        # d/dd [sigma^2 (1-h)] = -h e^2 / d^3 = -(2 sigma^2 / d) q h
        acc_d += q * h
    F = ld + logZ + s2 * acc / n - pull * ls / n
    dF_ds = dZs + 2.0 * sigma * acc_s / n
    dF_dd = 1.0 / d - (a / (d * d)) * dZA - 2.0 * s2 / d * acc_d / n
    return F, sigma * dF_ds - pull / n, d * dF_dd


@kernel
def estep_channel(e, n, a, sigma0, d0, sig_lo, sig_hi, d_lo, d_hi, max_iter, gtol, pull, H):
    """Maximum-likelihood (sigma, d) of one channel (Algorithm 2), warm-started at (sigma0, d0);
    pull > 0 adds the weak prior on sigma of the module doc.

    H (3,) = (h00, h01, h11) is the BFGS inverse-Hessian approximation in (log sigma, log d),
    read as the warm start and written back (H[0] <= 0 means "no curvature known yet"), so a
    stream's E-steps start from near-Newton steps. Returns (sigma, d, F, iterations, status);
    on NONFINITE/BAD_INPUT the start is returned.
    """
    if n < 1 or not (a > 0.0) or not (sigma0 > 0.0) or not (d0 > 0.0) or not (d_lo <= d_hi):
        return sigma0, d0, math.nan, 0, BAD_INPUT
    lo0 = math.log(sig_lo)
    hi0 = math.log(sig_hi)
    lo1 = math.log(d_lo)
    hi1 = math.log(d_hi)
    z0 = min(max(math.log(sigma0), lo0), hi0)
    z1 = min(max(math.log(d0), lo1), hi1)
    F, g0, g1 = estep_objective(z0, z1, e, n, a, pull)
    if not (math.isfinite(F) and math.isfinite(g0) and math.isfinite(g1)):
        return sigma0, d0, F, 0, NONFINITE
    # inverse-Hessian approximation; F ~ log d + s^2/(2 d^2) has curvature 2 in log d
    h00 = 0.5
    h01 = 0.0
    h11 = 0.5
    if H[0] > 0.0 and H[2] > 0.0 and H[0] * H[2] - H[1] * H[1] > 0.0 and math.isfinite(H[0] + H[1] + H[2]):
        h00 = H[0]
        h01 = H[1]
        h11 = H[2]
    status = NOT_CONVERGED
    it = 0
    while it < max_iter + FAR_EXTRA_ITER:
        free0 = not ((z0 <= lo0 and g0 > 0.0) or (z0 >= hi0 and g0 < 0.0))
        free1 = not ((z1 <= lo1 and g1 > 0.0) or (z1 >= hi1 and g1 < 0.0))
        pg0 = g0 if free0 else 0.0
        pg1 = g1 if free1 else 0.0
        if max(abs(pg0), abs(pg1)) <= gtol:
            status = OK
            break
        if it >= max_iter and max(abs(pg0), abs(pg1)) <= FAR_GTOL:
            break            # the cap: near enough for a generalised EM step
        it += 1
        if free0 and free1:
            p0 = -(h00 * g0 + h01 * g1)
            p1 = -(h01 * g0 + h11 * g1)
        else:
            p0 = -h00 * pg0
            p1 = -h11 * pg1
        if p0 * pg0 + p1 * pg1 >= 0.0:       # not a descent direction: restart from steepest descent
            h00, h01, h11 = 0.5, 0.0, 0.5
            p0 = -0.5 * pg0
            p1 = -0.5 * pg1
        pmax = max(abs(p0), abs(p1))
        alpha = 1.0 if pmax <= 2.0 else 2.0 / pmax   # at most a factor e^2 per step
        alpha0 = alpha
        accepted = False
        for _ in range(40):
            n0 = min(max(z0 + alpha * p0, lo0), hi0)
            n1 = min(max(z1 + alpha * p1, lo1), hi1)
            Fn, gn0, gn1 = estep_objective(n0, n1, e, n, a, pull)
            if math.isfinite(Fn) and math.isfinite(gn0) and math.isfinite(gn1):
                if Fn <= F + 1e-4 * (g0 * (n0 - z0) + g1 * (n1 - z1)):
                    accepted = True
                    break
            alpha *= 0.5
        pred = -(g0 * (n0 - z0) + g1 * (n1 - z1))
        if accepted and alpha == alpha0 and pred > 0.0 and (F - Fn) > 0.8 * pred:
            # Flat regions (sigma and d large, Section III-D): the full step was accepted and F
            # fell like its linear model (a quadratic model's Newton step gives half), so the
            # curvature is overestimated: keep doubling while F falls, up to the e^2 cap.
            pnorm = max(abs(p0), abs(p1))
            while 2.0 * alpha * pnorm <= 2.0:
                t0 = min(max(z0 + 2.0 * alpha * p0, lo0), hi0)
                t1 = min(max(z1 + 2.0 * alpha * p1, lo1), hi1)
                Ft, gt0, gt1 = estep_objective(t0, t1, e, n, a, pull)
                if not (math.isfinite(Ft) and math.isfinite(gt0) and math.isfinite(gt1)) or Ft >= Fn:
                    break
                alpha *= 2.0
                n0, n1, Fn, gn0, gn1 = t0, t1, Ft, gt0, gt1
        if not accepted:
            # no decrease possible at float resolution: we are at the minimum (or on a flat ridge)
            status = OK if max(abs(pg0), abs(pg1)) <= 1e3 * gtol else NOT_CONVERGED
            break
        s0 = n0 - z0
        s1 = n1 - z1
        y0 = gn0 - g0
        y1 = gn1 - g1
        sy = s0 * y0 + s1 * y1
        if sy > 1e-12 * math.sqrt((s0 * s0 + s1 * s1) * (y0 * y0 + y1 * y1)):
            # BFGS inverse update H <- (I - r s y^T) H (I - r y s^T) + r s s^T
            r = 1.0 / sy
            hy0 = h00 * y0 + h01 * y1
            hy1 = h01 * y0 + h11 * y1
            yhy = y0 * hy0 + y1 * hy1
            c = (1.0 + r * yhy) * r
            h00 = h00 + c * s0 * s0 - r * (hy0 * s0 + s0 * hy0)
            h01 = h01 + c * s0 * s1 - r * (hy0 * s1 + s0 * hy1)
            h11 = h11 + c * s1 * s1 - r * (hy1 * s1 + s1 * hy1)
        z0, z1, F, g0, g1 = n0, n1, Fn, gn0, gn1
        if max(abs(s0), abs(s1)) <= 1e-12:
            status = OK
            break
    H[0] = h00
    H[1] = h01
    H[2] = h11
    return math.exp(z0), math.exp(z1), F, it, status
