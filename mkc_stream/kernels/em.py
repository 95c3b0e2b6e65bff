"""MKC-EM, Algorithm 3: alternate the E-step (Algorithm 2) and the M-step (Algorithm 1)."""
import math

from .._numba import kernel
from . import OK, NOT_CONVERGED, NONFINITE
from .mstep import mstep_fixed_point
from .estep import estep_channel


@kernel
def truncation_bound(R, i, fixed_a, a_factor, Y):
    """a_i of the truncated domain [-a_i, a_i]: fixed, or a_factor * max_k |e_k(i)|.

    The paper leaves a free ("sufficiently big so that all e_k(i) are covered"); the data
    range is the smallest such a and the natural scale of a uniform outlier component. A
    floor keeps a > 0 when the fit is exact.
    """
    if fixed_a > 0.0:
        return fixed_a
    N = R.shape[0]
    amax = 0.0
    ymax = 0.0
    for k in range(N):
        amax = max(amax, abs(R[k, i]))
        ymax = max(ymax, abs(Y[k, i]))
    return max(a_factor * amax, 1e-12 * (1.0 + ymax))


@kernel
def mkc_em(X, Y, sigma, d, theta, fixed_a, a_factor, sig_lo, sig_hi, d_lo_frac, d_hi_frac,
           em_iter, em_tol, fp_max_iter, fp_tol, es_max_iter, es_gtol, es_pull,
           R, W, A, b, x, L, D, ebuf, tprev, a_out, Hes, hist_theta, hist_sigma, hist_d):
    """Run MKC-EM in place on (theta, sigma, d). Returns (em_rounds, fp_iters, status, cond).

    theta must hold a starting guess (the caller passes WLS with the initial d, as the paper
    initialises Algorithm 1). Hes (m, 3) carries each channel's E-step curvature across
    rounds (zeros: none yet). hist_* rows 0..em_rounds record the path (row 0 = after the
    initial Algorithm 1 run); they must have em_iter + 1 rows.
    """
    N, m, n = X.shape
    # Initialisation (Algorithm 3, line 1): Algorithm 1 at the initial (sigma, d).
    fp_total, status, cond = mstep_fixed_point(X, Y, sigma, d, theta, fp_max_iter, fp_tol, R, W, A, b, x, L, D)
    for j in range(n):
        hist_theta[0, j] = theta[j]
    for i in range(m):
        hist_sigma[0, i] = sigma[i]
        hist_d[0, i] = d[i]
    if status != OK and status != NOT_CONVERGED:
        return 0, fp_total, status, cond
    rounds = 0
    em_status = NOT_CONVERGED
    while rounds < em_iter:
        rounds += 1
        # E-step (Algorithm 2) per channel on the residuals of the current theta (R is current).
        dpar = 0.0
        for i in range(m):
            for k in range(N):
                ebuf[k] = R[k, i]
            a = truncation_bound(R, i, fixed_a, a_factor, Y)
            a_out[i] = a
            s_new, d_new, F, its, st = estep_channel(ebuf, N, a, sigma[i], d[i], sig_lo, sig_hi,
                                                     d_lo_frac * a, d_hi_frac * a, es_max_iter, es_gtol, es_pull, Hes[i])
            if st == OK or st == NOT_CONVERGED:
                dpar = max(dpar, abs(math.log(s_new / sigma[i])), abs(math.log(d_new / d[i])))
                sigma[i] = s_new
                d[i] = d_new
        # M-step (Algorithm 1) warm-started from the current theta.
        for j in range(n):
            tprev[j] = theta[j]      # to measure the EM step
        its, st, cond = mstep_fixed_point(X, Y, sigma, d, theta, fp_max_iter, fp_tol, R, W, A, b, x, L, D)
        fp_total += its
        for j in range(n):
            hist_theta[rounds, j] = theta[j]
        for i in range(m):
            hist_sigma[rounds, i] = sigma[i]
            hist_d[rounds, i] = d[i]
        if st != OK and st != NOT_CONVERGED:
            return rounds, fp_total, st, cond
        num = 0.0
        prev_norm = 0.0
        for j in range(n):
            num += (theta[j] - tprev[j]) ** 2
            prev_norm += tprev[j] ** 2
        if math.sqrt(num) <= em_tol * max(math.sqrt(prev_norm), 1e-300) and dpar <= 1e-3:
            em_status = OK
            break
    for j in range(n):
        if not math.isfinite(theta[j]):
            return rounds, fp_total, NONFINITE, cond
    return rounds, fp_total, em_status, cond
