/* normaliser.c: the normaliser Z(sigma, A) of the truncated MKC-induced pdf, eq. (17), and its
 * gradient; kernels/normaliser.py line by line.
 *
 * Z = 2 [ A exp(-sigma^2) + int_0^{min(A, u_c)} g(u) du ],  g = f - exp(-sigma^2),
 * f(u) = exp(-sigma^2 (1 - h)), h = exp(-u^2 / (2 sigma^2)). The floor is exact; the bounded integral
 * is composite Gauss-Legendre (10 nodes, the generated table) on panels sized to g's local scale,
 * about 6-15 panels for sigma in [0.05, 1e3]: a bounded cost (the loop cannot run away: each panel
 * advances u by at least min(1.5 min(1, sigma), 2 sigma, 10 sigma^2 / u) > 0 up to u_c). Per node
 * three libm calls: h = exp(-q) (or the series of 1 - h for small q), f, and g's expm1. A
 * single-precision E-step uses the float table, longer series (mkc__omh_terms_f), an integrand for
 * dZ/dsigma without cancellation and compensated sums.
 */
#define MKC_TABLES_WANT_GL
#include "mkc_internal.h"

/* u_c with g(u_c) = TAU: sigma^2 h = log1p(TAU exp(sigma^2)), computed without overflow. */
mkc_ereal mkc__cut_point(mkc_ereal sigma)
{
    mkc_ereal s2 = sigma * sigma;
    mkc_ereal x = s2 + EC(MKC_LOG_TAU);          /* log(TAU exp(sigma^2)) */
    mkc_ereal L, h_c;
    if (x > EC(30.0))
        L = x + MKC_LOG1P_E(MKC_EXP_E(-x));
    else
        L = MKC_LOG1P_E(MKC_EXP_E(x));
    h_c = L / s2;
    if (h_c >= EC(1.0))
        return EC(0.0);
    return sigma * MKC_SQRT_E(EC(-2.0) * MKC_LOG_E(h_c));
}

#if MKC_ESTEP_DOUBLE
/* (1 - h, h) with h = e^-q from at most one exp: omh = q - q^2/2 + q^3/6 - q^4/24 + q^5/120 for
 * q < 1e-3, where 1 - h would cancel (f = exp(-sigma^2 omh) needs omh to a few ulps relative). */
static void omh_h(mkc_ereal q, mkc_ereal *omh, mkc_ereal *h)
{
    if (q < EC(1e-3)) {
        mkc_ereal o = q * (EC(1.0) - q * (EC(0.5) - q * (EC(1.0 / 6.0) - q * (EC(1.0 / 24.0) - q * (EC(1.0 / 120.0))))));
        *omh = o;
        *h = EC(1.0) - o;
        return;
    }
    *h = MKC_EXP_E(-q);
    *omh = EC(1.0) - *h;
}
#else
/* mkc_internal.h: (1 - h, 1 - (1 + q) h, h) for the single-precision E-step (estep.c, and the
 * integrand below); out of line, one copy for both */
void mkc__omh_terms_f(float q, float *omh, float *omh_qh, float *h)
{
    if (q < 0.5f) {
        float o = q * (1.0f - q * (0.5f - q * (1.0f / 6.0f - q * (1.0f / 24.0f - q * (1.0f / 120.0f
                  - q * (1.0f / 720.0f - q * (1.0f / 5040.0f - q * (1.0f / 40320.0f))))))));
        *omh = o;
        *omh_qh = q * q * (0.5f - q * (1.0f / 3.0f - q * (0.125f - q * (1.0f / 30.0f - q * (1.0f / 144.0f
                  - q * (1.0f / 840.0f - q * (1.0f / 5760.0f - q * (1.0f / 45360.0f))))))));
        *h = 1.0f - o;
        return;
    }
    *h = expf(-q);
    *omh = 1.0f - *h;
    *omh_qh = *omh - q * *h;
}
#endif

/* Head (|u| < 3 max(1, sigma)): width ~1 (big sigma) or ~sigma (small sigma) bump. Tail: g ~
 * exp(-u^2/(2 sigma^2)), whose log changes by u w / sigma^2 over a panel. */
static mkc_ereal panel_width(mkc_ereal u, mkc_ereal sigma)
{
    if (u < EC(3.0) * mkc__max_e(EC(1.0), sigma))
        return EC(1.5) * mkc__min_e(EC(1.0), sigma);
    return mkc__min_e(EC(2.0) * sigma, EC(10.0) * sigma * sigma / u);
}

mkc_ereal mkc__log_normaliser_grad(mkc_ereal sigma, mkc_ereal A, mkc_ereal *d_sigma, mkc_ereal *d_A)
{
    mkc_ereal s2 = sigma * sigma;
    mkc_ereal floor_ = MKC_EXP_E(-s2);
    mkc_ereal uc = mkc__min_e(A, mkc__cut_point(sigma));
    mkc_ereal Ig = EC(0.0), Ids = EC(0.0), u = EC(0.0);
    mkc_ereal Z, dZ_ds, fA, dZ_dA;
    int j;
#if !MKC_ESTEP_DOUBLE
    mkc_ereal cIg = EC(0.0), cIds = EC(0.0);      /* Kahan compensations */
#endif
    while (u < uc) {
        mkc_ereal w = panel_width(u, sigma);
        mkc_ereal ub = mkc__min_e(u + w, uc);
        mkc_ereal span = ub - u;
#if !MKC_ESTEP_DOUBLE
        /* d/dsigma of the integrand, 2 sigma (f h - g) + f h x^2 / sigma, is (g = f - floor,
         * x^2 / sigma = 2 sigma q) 2 sigma (floor - f (1 - h - q h)): the two O(x^2 / sigma) terms
         * cancel analytically instead of in float. */
        for (j = 0; j < MKC_GL_ORDER; j++) {
            mkc_ereal x = u + span * mkc_gl_nodes[j];
            mkc_ereal q = x * x / (EC(2.0) * s2);
            mkc_ereal omh, omh_qh, h, f, g, wj = span * mkc_gl_weights[j];
            mkc__omh_terms_f(q, &omh, &omh_qh, &h);
            f = MKC_EXP_E(-s2 * omh);
            g = f * (-MKC_EXPM1_E(-s2 * h));
            mkc__kahan_add_f(&Ig, &cIg, wj * g);
            mkc__kahan_add_f(&Ids, &cIds, wj * (EC(2.0) * sigma * (floor_ - f * omh_qh)));
        }
#else
        for (j = 0; j < MKC_GL_ORDER; j++) {
            mkc_ereal x = u + span * EC(mkc_gl_nodes[j]);
            mkc_ereal q = x * x / (EC(2.0) * s2);
            mkc_ereal omh, h, f, g;
            omh_h(q, &omh, &h);
            f = MKC_EXP_E(-s2 * omh);                   /* f = exp(-sigma^2 (1 - h)) */
            g = f * (-MKC_EXPM1_E(-s2 * h));            /* g = f - exp(-sigma^2), without cancellation */
            mkc_ereal wj = span * EC(mkc_gl_weights[j]);
            Ig += wj * g;
            Ids += wj * (EC(2.0) * sigma * (f * h - g) + f * h * x * x / sigma);
        }
#endif
        u = ub;
    }
    Z = EC(2.0) * (A * floor_ + Ig);
    dZ_ds = EC(2.0) * (EC(-2.0) * sigma * A * floor_ + Ids);
    fA = MKC_EXP_E(-s2 * (-MKC_EXPM1_E(-A * A / (EC(2.0) * s2))));
    dZ_dA = EC(2.0) * fA;
    *d_sigma = dZ_ds / Z;
    *d_A = dZ_dA / Z;
    return MKC_LOG_E(Z);
}
