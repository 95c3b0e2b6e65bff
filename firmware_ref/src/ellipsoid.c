/* ellipsoid.c: the ellipsoid of the appendix, eqs. (36)-(41), and its calibration (b, S, F);
 * calib/ellipsoid.py geometry_from_theta, raw_geometry, calibration_from_geometry.
 *
 * a1 x^2 + a2 y^2 + a3 z^2 + a4 xy + a5 xz + a6 yz + a7 x + a8 y + a9 z = 1 is x^T A x + B^T x = 1;
 * centre r0 = -A^-1 B / 2 (38), shape M = A / (1 + r0^T A r0) so (m - r0)^T M (m - r0) = 1.
 * Calibration: S = F M^(1/2) with the symmetric square root Q diag(sqrt l) Q^T (cyclic Jacobi,
 * linalg.c), F = det(M)^(-1/6) the geometric-mean radius, so det S = 1. Computed in mkc_creal:
 * double in the double and float builds, float in the all-float one (MKC_CHECKPOINT_DOUBLE, a few
 * hundred flops per checkpoint).
 */
#include "mkc_internal.h"

static void quadric_from_theta(const mkc_real *t, mkc_creal A[3][3], mkc_creal *B)
{
    A[0][0] = (mkc_creal)t[0];
    A[1][1] = (mkc_creal)t[1];
    A[2][2] = (mkc_creal)t[2];
    A[0][1] = A[1][0] = (mkc_creal)t[3] / CR(2.0);
    A[0][2] = A[2][0] = (mkc_creal)t[4] / CR(2.0);
    A[1][2] = A[2][1] = (mkc_creal)t[5] / CR(2.0);
    B[0] = (mkc_creal)t[6];
    B[1] = (mkc_creal)t[7];
    B[2] = (mkc_creal)t[8];
}

static void eig3(const mkc_creal A[3][3], mkc_creal *w, mkc_creal V[9][9])
{
    mkc_creal a[9][9];
    int i, j;
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++)
            a[i][j] = A[i][j];
    mkc__jacobi_eigen(a, 3, w, V);
}

int mkc__geometry_from_theta(const mkc_real *theta, mkc__geometry *g, mkc_mag_reason *reason)
{
    mkc_creal A[3][3], B[3], eigA[3], r0[3], Ar0[3], k, lam[3];
    int i, j;
    /* A and B are finite exactly when theta is (halving keeps a value finite or not) */
    for (i = 0; i < 9; i++)
        if (!MKC_ISFINITE(theta[i]))
            return MKC_REASON_NOT_FINITE;
    quadric_from_theta(theta, A, B);
    eig3((const mkc_creal(*)[3])A, eigA, NULL);
    if (eigA[0] * eigA[2] <= CR(0.0)) {
        reason->v[0] = MKC_REASON_VALUE(eigA[0]);
        reason->v[1] = MKC_REASON_VALUE(eigA[1]);
        reason->v[2] = MKC_REASON_VALUE(eigA[2]);
        return MKC_REASON_INDEFINITE;
    }
    if (mkc__solve3((const mkc_creal(*)[3])A, B, r0) != MKC_OK)
        return MKC_REASON_SINGULAR;
    for (i = 0; i < 3; i++)
        r0[i] = -CR(0.5) * r0[i];
    /* k = 1 + r0^T A r0, as (r0 @ A) @ r0 */
    for (j = 0; j < 3; j++)
        Ar0[j] = r0[0] * A[0][j] + r0[1] * A[1][j] + r0[2] * A[2][j];
    k = CR(1.0) + (Ar0[0] * r0[0] + Ar0[1] * r0[1] + Ar0[2] * r0[2]);
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++)
            g->M[i][j] = A[i][j] / k;
    eig3((const mkc_creal(*)[3])g->M, lam, NULL);
    if (!(lam[0] > CR(0.0))) {
        reason->v[0] = MKC_REASON_VALUE(k);
        return MKC_REASON_EMPTY;
    }
    for (i = 0; i < 3; i++)
        g->centre[i] = r0[i];
    return MKC_REASON_NONE;
}

/* Map a geometry fitted in normalised coordinates (m - c0) / s0 back to raw sensor units. */
void mkc__raw_geometry(mkc__geometry *g, const mkc_real *c0, mkc_real s0)
{
    mkc_creal s = (mkc_creal)s0, s2 = s * s;
    int i, j;
    for (i = 0; i < 3; i++) {
        g->centre[i] = (mkc_creal)c0[i] + s * g->centre[i];
        for (j = 0; j < 3; j++)
            g->M[i][j] = g->M[i][j] / s2;
    }
}

/* (b, S, F) with m_cal = S (m - b), S symmetric positive definite with det S = 1. */
void mkc__calibration_from_geometry(const mkc__geometry *g, mkc_creal b[3], mkc_creal S[3][3], mkc_creal *F)
{
    mkc_creal lam[3], Q[9][9], P[3][3], f;
    int i, j, k;
    eig3(g->M, lam, Q);
#if MKC_CREAL_FLOAT
    /* f = (l0 l1 l2)^(-1/6) = 1 / cbrt(sqrt(l0) sqrt(l1) sqrt(l2)): powf's exponent -1/6 is off by
     * 3e-8 relative in float, which times |ln(l0 l1 l2)| (~40 for fields of ~1000 counts) is ~4 ulps
     * of f; the cube root of the square roots is within ~1.5 ulps and cannot underflow before F^3 does */
    {
        mkc_creal r[3];
        for (k = 0; k < 3; k++)
            r[k] = sqrtf(lam[k]);
        f = CR(1.0) / MKC_CBRTF(r[0] * r[1] * r[2]);
        for (i = 0; i < 3; i++)
            for (k = 0; k < 3; k++)
                P[i][k] = f * (Q[i][k] * r[k]);
    }
#else
    f = MKC_POW_C(lam[0] * lam[1] * lam[2], -CR(1.0) / CR(6.0));
    for (i = 0; i < 3; i++)
        for (k = 0; k < 3; k++)
            P[i][k] = f * (Q[i][k] * MKC_SQRT_C(lam[k]));
#endif
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++)
            S[i][j] = P[i][0] * Q[j][0] + P[i][1] * Q[j][1] + P[i][2] * Q[j][2];
    for (i = 0; i < 3; i++) {
        for (j = i + 1; j < 3; j++) {
            mkc_creal s = CR(0.5) * (S[i][j] + S[j][i]);
            S[i][j] = S[j][i] = s;
        }
        b[i] = g->centre[i];
    }
    *F = f;
}
