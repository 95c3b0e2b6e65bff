/* estep.c: the E-step, per-channel maximum likelihood of (sigma, d), eqs. (29)-(31), Algorithm 2;
 * kernels/estep.py line by line.
 *
 * F(sigma, d) = log d + log Z(sigma, a/d) + (sigma^2 / N) sum_k (1 - exp(-e_k^2 / (2 d^2 sigma^2)))
 *               - (pull / N) log sigma
 * (the last term a weak prior on sigma, see kernels/estep.py; the paper's "log(c_i - d_i)" read as log(c_i / d_i)), minimised over (log sigma, log d) inside a
 * box by projected BFGS with Armijo backtracking, analytic gradients, at most max_iter iterations
 * (+ FAR_EXTRA_ITER while far from the optimum; each with at most 40 halvings and a bounded
 * doubling), warm-started from H. A non-finite trial
 * is a failed step, so no NaN reaches the state.
 * A single-precision E-step (MKC_ESTEP_DOUBLE = 0) evaluates the same F and gradient through
 * cancellation-free series with compensated sums (mkc_internal.h), and updates the BFGS curvature
 * only from gradient changes above their rounding noise.
 */
#include "mkc_internal.h"

#if MKC_ESTEP_DOUBLE
/* (1 - h, (1 - h) - q h, h) with h = e^-q from one exp; series for small q (no cancellation). */
static void omh_terms(mkc_ereal q, mkc_ereal *omh, mkc_ereal *omh_qh, mkc_ereal *h)
{
    if (q < EC(1e-3)) {
        mkc_ereal o = q * (EC(1.0) - q * (EC(0.5) - q * (EC(1.0 / 6.0) - q * (EC(1.0 / 24.0)))));
        *omh = o;
        *omh_qh = q * q * (EC(0.5) - q * (EC(1.0 / 3.0) - q * EC(0.125)));
        *h = EC(1.0) - o;
        return;
    }
    *h = MKC_EXP_E(-q);
    *omh = EC(1.0) - *h;
    *omh_qh = *omh - q * *h;
}
#endif

/* F and its gradient in (log sigma, log d) for the residuals e[:n] truncated to [-a, a]. The caller
 * passes the squares e2[k] = e[k] e[k]: the reference's q = e[k] * e[k] * inv is (e[k] e[k]) inv,
 * so squaring once per E-step instead of once per evaluation gives the same q. */
static mkc_ereal objective(mkc_ereal ls, mkc_ereal ld, const mkc_real *e2, int n, mkc_ereal a, mkc_ereal pull,
                           mkc_ereal *g0, mkc_ereal *g1, mkc_ereal *nu)
{
    mkc_ereal sigma = MKC_EXP_E(ls);
    mkc_ereal d = MKC_EXP_E(ld);
    mkc_ereal s2 = sigma * sigma;
    mkc_ereal dZs, dZA, logZ, inv, F, dF_ds, dF_dd;
    mkc_ereal acc = EC(0.0), acc_s = EC(0.0), acc_d = EC(0.0);
    int k;
    logZ = mkc__log_normaliser_grad(sigma, a / d, &dZs, &dZA);
    inv = EC(1.0) / (EC(2.0) * d * d * s2);
    k = 0;
#if !MKC_ESTEP_DOUBLE
    {
        /* single precision: cancellation-free terms (mkc__omh_terms_f) and compensated sums */
        mkc_ereal c_acc = EC(0.0), c_s = EC(0.0), c_d = EC(0.0);
        for (; k < n; k++) {
            mkc_ereal q = e2[k] * inv;
            mkc_ereal omh, omh_qh, h;
            mkc__omh_terms_f(q, &omh, &omh_qh, &h);
            mkc__kahan_add_f(&acc, &c_acc, omh);
            mkc__kahan_add_f(&acc_s, &c_s, omh_qh);
            mkc__kahan_add_f(&acc_d, &c_d, q * h);
        }
    }
#else
    /* Two residuals per pass: when both take the series branch of omh_terms, its statements are
     * written out for the pair side by side (isomorphic, so the compiler may pair them into SIMD
     * operations); every term is computed as omh_terms computes it and the sums still receive
     * the terms one at a time in ascending k, so the results are the same bits. */
    for (; k + 1 < n; k += 2) {
        mkc_ereal q0 = (mkc_ereal)e2[k] * inv, q1 = (mkc_ereal)e2[k + 1] * inv;
        mkc_ereal omh0, omh1, omh_qh0, omh_qh1, h0, h1;
        if (q0 < EC(1e-3) && q1 < EC(1e-3)) {
            omh0 = q0 * (EC(1.0) - q0 * (EC(0.5) - q0 * (EC(1.0 / 6.0) - q0 * (EC(1.0 / 24.0)))));
            omh1 = q1 * (EC(1.0) - q1 * (EC(0.5) - q1 * (EC(1.0 / 6.0) - q1 * (EC(1.0 / 24.0)))));
            omh_qh0 = q0 * q0 * (EC(0.5) - q0 * (EC(1.0 / 3.0) - q0 * EC(0.125)));
            omh_qh1 = q1 * q1 * (EC(0.5) - q1 * (EC(1.0 / 3.0) - q1 * EC(0.125)));
            h0 = EC(1.0) - omh0;
            h1 = EC(1.0) - omh1;
        } else {
            omh_terms(q0, &omh0, &omh_qh0, &h0);
            omh_terms(q1, &omh1, &omh_qh1, &h1);
        }
        acc += omh0;
        acc += omh1;
        acc_s += omh_qh0;    /* d/dsigma [sigma^2 (1-h)] = (2 sigma)(1 - h - q h) */
        acc_s += omh_qh1;
        acc_d += q0 * h0;    /* d/dd [sigma^2 (1-h)] = -(2 sigma^2 / d) q h */
        acc_d += q1 * h1;
    }
    for (; k < n; k++) {
        mkc_ereal q = (mkc_ereal)e2[k] * inv;
        mkc_ereal omh, omh_qh, h;
        omh_terms(q, &omh, &omh_qh, &h);
        acc += omh;
        acc_s += omh_qh;
        acc_d += q * h;
    }
#endif
    F = ld + logZ + s2 * acc / (mkc_ereal)n - pull * ls / (mkc_ereal)n;    /* the weak prior on sigma */
    dF_ds = dZs + EC(2.0) * sigma * acc_s / (mkc_ereal)n;
    dF_dd = EC(1.0) / d - (a / (d * d)) * dZA - EC(2.0) * s2 / d * acc_d / (mkc_ereal)n;
    *g0 = sigma * dF_ds - pull / (mkc_ereal)n;
    *g1 = d * dF_dd;
#if !MKC_ESTEP_DOUBLE
    /* rounding noise of g0, g1: MKC_GRAD_NOISE_ULPS ulps of the magnitudes of the terms each sums */
    nu[0] = EC(MKC_GRAD_NOISE_ULPS) * EC(MKC_FLT_EPS) * (MKC_FABS_E(sigma * dZs) + MKC_FABS_E(sigma * (dF_ds - dZs))
                                                        + pull / (mkc_ereal)n);
    nu[1] = EC(MKC_GRAD_NOISE_ULPS) * EC(MKC_FLT_EPS) * (EC(1.0) + MKC_FABS_E(a / d * dZA)
                                                        + MKC_FABS_E(EC(2.0) * s2 * acc_d / (mkc_ereal)n));
#else
    (void)nu;
#endif
    return F;
}

/* exported for tests and tools; the optimiser calls the file-local objective (inlinable also in
 * a shared object) */
mkc_ereal mkc__estep_objective(mkc_ereal ls, mkc_ereal ld, const mkc_real *e2, int n, mkc_ereal a, mkc_ereal pull,
                               mkc_ereal *g0, mkc_ereal *g1)
{
    mkc_ereal nu[2];
    return objective(ls, ld, e2, n, a, pull, g0, g1, nu);
}

/* 1 when F and its gradient (g0, g1) are finite */
MKC_NOINLINE static int fin3(mkc_ereal a, mkc_ereal b, mkc_ereal c)
{
    return MKC_ISFINITE(a) && MKC_ISFINITE(b) && MKC_ISFINITE(c);
}

/* 1 when coordinate z (gradient g) may move: not held at a bound of [lo, hi] by its gradient */
MKC_NOINLINE static int is_free(mkc_ereal z, mkc_ereal g, mkc_ereal lo, mkc_ereal hi)
{
    return !((z <= lo && g > EC(0.0)) || (z >= hi && g < EC(0.0)));
}
#define CLAMP(v, lo, hi) mkc__min_e(mkc__max_e((v), (lo)), (hi))

/* Maximum-likelihood (sigma, d) of one channel from the squared residuals e2[:n], warm-started at
 * (sigma0, d0); pull > 0 adds the weak prior on sigma. H (3) = (h00, h01,
 * h11), the BFGS inverse-Hessian approximation in (log sigma, log d), is read as the warm start and
 * written back (H[0] <= 0: none known). On MKC_NONFINITE / MKC_BAD_INPUT the start is returned. */
int mkc__estep_channel(const mkc_real *e2, int n, mkc_ereal a, mkc_ereal sigma0, mkc_ereal d0, mkc_ereal sig_lo,
                       mkc_ereal sig_hi, mkc_ereal d_lo, mkc_ereal d_hi, int max_iter, mkc_ereal gtol, mkc_ereal pull,
                       mkc_ereal *H, mkc_ereal *sigma_out, mkc_ereal *d_out, mkc_ereal *F_out, int *iters)
{
    mkc_ereal lo0, hi0, lo1, hi1, z0, z1, F, g0, g1, h00, h01, h11;
    mkc_ereal n0 = EC(0.0), n1 = EC(0.0), Fn = EC(0.0), gn0 = EC(0.0), gn1 = EC(0.0);
    mkc_ereal nu[2] = {EC(0.0), EC(0.0)}, nun[2] = {EC(0.0), EC(0.0)};   /* gradient noise (float E-step) */
    int status = MKC_NOT_CONVERGED, it = 0;
    *iters = 0;
    if (n < 1 || !(a > EC(0.0)) || !(sigma0 > EC(0.0)) || !(d0 > EC(0.0)) || !(d_lo <= d_hi)) {
        *sigma_out = sigma0;
        *d_out = d0;
        *F_out = EC(NAN);
        return MKC_BAD_INPUT;
    }
    lo0 = MKC_LOG_E(sig_lo);
    hi0 = MKC_LOG_E(sig_hi);
    lo1 = MKC_LOG_E(d_lo);
    hi1 = MKC_LOG_E(d_hi);
    z0 = CLAMP(MKC_LOG_E(sigma0), lo0, hi0);
    z1 = CLAMP(MKC_LOG_E(d0), lo1, hi1);
    F = objective(z0, z1, e2, n, a, pull, &g0, &g1, nu);
    if (!fin3(F, g0, g1)) {
        *sigma_out = sigma0;
        *d_out = d0;
        *F_out = F;
        return MKC_NONFINITE;
    }
    /* inverse-Hessian approximation; F ~ log d + s^2/(2 d^2) has curvature 2 in log d */
    h00 = EC(0.5);
    h01 = EC(0.0);
    h11 = EC(0.5);
    if (H[0] > EC(0.0) && H[2] > EC(0.0) && H[0] * H[2] - H[1] * H[1] > EC(0.0) && MKC_ISFINITE(H[0] + H[1] + H[2])) {
        h00 = H[0];
        h01 = H[1];
        h11 = H[2];
    }
    /* A capped E-step (a stream's generalised EM step) may run FAR_EXTRA_ITER iterations beyond
     * its cap while the projected gradient is above FAR_GTOL: after a burst enters a clean window
     * the optimum jumps, and max_iter iterations would leave a stale kernel for several checkpoints. */
    while (it < max_iter + MKC_FAR_EXTRA_ITER) {
        int free0, free1, accepted = 0, ls;
        mkc_ereal pg0, pg1, pgmax, p0, p1, pmax, alpha, alpha0, pred, s0, s1, y0, y1, sy;
        free0 = is_free(z0, g0, lo0, hi0);
        free1 = is_free(z1, g1, lo1, hi1);
        pg0 = free0 ? g0 : EC(0.0);
        pg1 = free1 ? g1 : EC(0.0);
        pgmax = mkc__max_e(MKC_FABS_E(pg0), MKC_FABS_E(pg1));    /* the projected gradient's size */
        if (pgmax <= gtol) {
            status = MKC_OK;
            break;
        }
        if (it >= max_iter && pgmax <= EC(MKC_FAR_GTOL))
            break;            /* the cap: near enough for a generalised EM step */
        it += 1;
        if (free0 && free1) {
            p0 = -(h00 * g0 + h01 * g1);
            p1 = -(h01 * g0 + h11 * g1);
        } else {
            p0 = -h00 * pg0;
            p1 = -h11 * pg1;
        }
        if (p0 * pg0 + p1 * pg1 >= EC(0.0)) {    /* not a descent direction: restart from steepest descent */
            h00 = EC(0.5);
            h01 = EC(0.0);
            h11 = EC(0.5);
            p0 = EC(-0.5) * pg0;
            p1 = EC(-0.5) * pg1;
        }
        pmax = mkc__max_e(MKC_FABS_E(p0), MKC_FABS_E(p1));
        alpha = pmax <= EC(2.0) ? EC(1.0) : EC(2.0) / pmax;   /* at most a factor e^2 per step */
        alpha0 = alpha;
        for (ls = 0; ls < 40; ls++) {
            n0 = CLAMP(z0 + alpha * p0, lo0, hi0);
            n1 = CLAMP(z1 + alpha * p1, lo1, hi1);
            Fn = objective(n0, n1, e2, n, a, pull, &gn0, &gn1, nun);
            if (fin3(Fn, gn0, gn1)) {
                if (Fn <= F + EC(1e-4) * (g0 * (n0 - z0) + g1 * (n1 - z1))) {
                    accepted = 1;
                    break;
                }
            }
            alpha *= EC(0.5);
        }
        pred = -(g0 * (n0 - z0) + g1 * (n1 - z1));
        if (accepted && alpha == alpha0 && pred > EC(0.0) && (F - Fn) > EC(0.8) * pred) {
            /* Flat regions (sigma and d large, Section III-D): the full step was accepted and F fell
             * like its linear model, so the curvature is overestimated: keep doubling while F
             * falls, up to the e^2 cap. */
            while (EC(2.0) * alpha * pmax <= EC(2.0)) {   /* pmax: p0, p1 as above */
                mkc_ereal t0 = CLAMP(z0 + EC(2.0) * alpha * p0, lo0, hi0);
                mkc_ereal t1 = CLAMP(z1 + EC(2.0) * alpha * p1, lo1, hi1);
                mkc_ereal gt0, gt1;
                mkc_ereal nut[2];
                mkc_ereal Ft = objective(t0, t1, e2, n, a, pull, &gt0, &gt1, nut);
                if (!fin3(Ft, gt0, gt1) || Ft >= Fn)
                    break;
                alpha *= EC(2.0);
                n0 = t0;
                n1 = t1;
                Fn = Ft;
                gn0 = gt0;
                gn1 = gt1;
                nun[0] = nut[0];
                nun[1] = nut[1];
            }
        }
        if (!accepted) {
            /* no decrease possible at float resolution: at the minimum (or on a flat ridge) */
            status = pgmax <= EC(1e3) * gtol ? MKC_OK : MKC_NOT_CONVERGED;
            break;
        }
        s0 = n0 - z0;
        s1 = n1 - z1;
        y0 = gn0 - g0;
        y1 = gn1 - g1;
        sy = s0 * y0 + s1 * y1;
#if MKC_ESTEP_DOUBLE
        if (sy > EC(1e-12) * MKC_SQRT_E((s0 * s0 + s1 * s1) * (y0 * y0 + y1 * y1))) {
#else
        /* and only a curvature pair that float resolves: s^T y above the rounding noise of the two
         * gradients (on the flat ridge, or once the steps are tiny, y is noise, and a BFGS update
         * from it would carry a wrong curvature into every later warm-started E-step) */
        if (sy > EC(1e-12) * MKC_SQRT_E((s0 * s0 + s1 * s1) * (y0 * y0 + y1 * y1))
            && sy > MKC_FABS_E(s0) * (nu[0] + nun[0]) + MKC_FABS_E(s1) * (nu[1] + nun[1])) {
#endif
            /* BFGS inverse update H <- (I - r s y^T) H (I - r y s^T) + r s s^T */
            mkc_ereal r = EC(1.0) / sy;
            mkc_ereal hy0 = h00 * y0 + h01 * y1;
            mkc_ereal hy1 = h01 * y0 + h11 * y1;
            mkc_ereal yhy = y0 * hy0 + y1 * hy1;
            mkc_ereal c = (EC(1.0) + r * yhy) * r;
            h00 = h00 + c * s0 * s0 - r * (hy0 * s0 + s0 * hy0);
            h01 = h01 + c * s0 * s1 - r * (hy0 * s1 + s0 * hy1);
            h11 = h11 + c * s1 * s1 - r * (hy1 * s1 + s1 * hy1);
        }
        z0 = n0;
        z1 = n1;
        F = Fn;
        g0 = gn0;
        g1 = gn1;
        nu[0] = nun[0];
        nu[1] = nun[1];
        if (mkc__max_e(MKC_FABS_E(s0), MKC_FABS_E(s1)) <= EC(1e-12)) {
            status = MKC_OK;
            break;
        }
    }
    H[0] = h00;
    H[1] = h01;
    H[2] = h11;
    *sigma_out = MKC_EXP_E(z0);
    *d_out = MKC_EXP_E(z1);
    *F_out = F;
    *iters = it;
    return status;
}
