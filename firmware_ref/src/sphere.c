/* sphere.c: the sphere fit that sets the calibrator's final feature normalisation;
 * calib/ellipsoid.py sphere_fit and robust_sphere_fit, calib/quality.py sphere_coverage.
 *
 * |m - b|^2 = F^2 as the linear least-squares problem |m'|^2 = 2 b'^T m' + k in centred, scaled
 * coordinates m' = (m - c) / scale (c the mean, scale the rms distance to it). The Python reference
 * calls LAPACK's SVD least squares; here the 4x4 normal equations are solved and then refined twice
 * with the residual recomputed from the data (semi-normal equations with refinement), which
 * reaches the accuracy of an orthogonal solver for these well-scaled columns without storing the
 * N x 4 matrix. The all-float build (MKC_CHECKPOINT_DOUBLE=0) forms the residuals and G^T r in
 * float-float (mkc_ff.h), so its fit rounds to the same floats as the double build's: the stream's
 * normalisation and its cold starts begin there, and one ulp of the radius is enough to move a
 * later E-step on a flat likelihood. Scratch: g->core.ebuf (the medians' copies, then per-row sums); the
 * robust passes' selection is a bit mask.
 */
#include "mkc_internal.h"
#include "mkc_ff.h"

/* the robust passes' selection: row k kept when bit k of keep is set (all rows when use_mask is 0) */
typedef struct sel {
    int use_mask;
    uint32_t keep[(MKC_W + 31) / 32];
} sel;

static int selected(const mkc_mag_t *g, const sel *m, int k)
{
    (void)g;
    return !m->use_mask || (m->keep[k >> 5] >> (k & 31) & 1u);
}

/* Solve the symmetric positive definite 4x4 N x = r by Cholesky (mkc_creal); 0 if not PD. */
static int chol4(const mkc_creal N[4][4], const mkc_creal *r, mkc_creal *x)
{
    mkc_creal L[4][4];
    int i, j, k;
    for (j = 0; j < 4; j++) {
        mkc_creal s = N[j][j];
        for (k = 0; k < j; k++)
            s -= L[j][k] * L[j][k];
        if (!(s > CR(0.0)) || !MKC_ISFINITE(s))
            return 0;
        L[j][j] = MKC_SQRT_C(s);
        for (i = j + 1; i < 4; i++) {
            mkc_creal t = N[i][j];
            for (k = 0; k < j; k++)
                t -= L[i][k] * L[j][k];
            L[i][j] = t / L[j][j];
        }
    }
    for (i = 0; i < 4; i++) {
        mkc_creal s = r[i];
        for (k = 0; k < i; k++)
            s -= L[i][k] * x[k];
        x[i] = s / L[i][i];
    }
    for (i = 3; i >= 0; i--) {
        mkc_creal s = x[i];
        for (k = i + 1; k < 4; k++)
            s -= L[k][i] * x[k];
        x[i] = s / L[i][i];
    }
    return 1;
}

#if MKC_CREAL_FLOAT
/* Passes of the float build: the first solves in float (x = 0, so the residual is y), each
 * refinement gains what a float Cholesky solve of the normal equations gives (~1e-6 relative
 * times their condition, which a window covering part of the sphere raises to ~1e2): two reach
 * the double build's float-rounded solution on every golden vector, the third is margin. */
#define MKC_SPHERE_PASSES 4
/* One pass over the selected rows u = (m - c) / scale: rhs = G^T (y - G x) with G's rows
 * [2 u, 1] and y = |u|^2; N = G^T G on the first pass (float: it only sets how fast the passes
 * converge). After the first, the residuals and their sums are float-float (x too): in float the
 * residual would carry the rounding of |u|^2 (1/2 ulp of 1) into x, and the sum G^T r, whose
 * terms cancel to the fit's noise, ~sqrt(n) ulps of them: either is enough to round the sphere's
 * centre or radius to the neighbouring float. */
static void sphere_pass(const mkc_mag_t *g, int count, const sel *m, const float *c, float scale, const mkc_ff *x,
                        float N[4][4], float *rhs, int first)
{
    mkc_ff acc[4] = {{0.0f, 0.0f}, {0.0f, 0.0f}, {0.0f, 0.0f}, {0.0f, 0.0f}};
    int k, j, p, q;
    for (k = 0; k < count; k++) {
        mkc_ff r = {0.0f, 0.0f};
        float u[3], row[4];
        if (!selected(g, m, k))
            continue;
        for (j = 0; j < 3; j++) {
            u[j] = (g->raw[k][j] - c[j]) / scale;
            row[j] = 2.0f * u[j];
        }
        row[3] = 1.0f;
        if (first) {
            r.hi = (u[0] * u[0] + u[1] * u[1]) + u[2] * u[2];
            for (p = 0; p < 4; p++) {
                acc[p].hi += row[p] * r.hi;
                for (q = 0; q <= p; q++)
                    N[p][q] += row[p] * row[q];
            }
            continue;
        }
        /* r = |u|^2 - (2 u^T x[0..2] + x[3]): a cascaded sum of exact products */
        for (j = 0; j < 3; j++)
            mkc__dot2_prod(&r, u[j], u[j]);
        for (j = 0; j < 4; j++) {
            mkc__dot2_prod(&r, -row[j], x[j].hi);
            r.lo -= row[j] * x[j].lo;
        }
        r = mkc__ff_make(r.hi, r.lo);
        for (p = 0; p < 4; p++) {
            mkc__dot2_prod(&acc[p], row[p], r.hi);
            acc[p].lo += row[p] * r.lo;
        }
    }
    for (p = 0; p < 4; p++)
        rhs[p] = acc[p].hi + acc[p].lo;
}
#else
#define MKC_SPHERE_PASSES 3       /* the solve and two refinements, as the reference (calib/portable.py) */
#endif

/* sphere_fit on the selected rows of raw[:count]; returns 0 when the fit is not a sphere. */
static int sphere_fit(mkc_mag_t *g, int count, const sel *m, mkc_real *b_out, mkc_real *F_out)
{
    mkc_real c[3] = {RC(0.0), RC(0.0), RC(0.0)}, ref[3], scale, F2, bb[3], kk;
    mkc_creal N[4][4], rhs[4], x[4] = {CR(0.0), CR(0.0), CR(0.0), CR(0.0)}, dx[4];
#if MKC_CREAL_FLOAT
    mkc_ff xf[4] = {{0.0f, 0.0f}, {0.0f, 0.0f}, {0.0f, 0.0f}, {0.0f, 0.0f}};
#endif
    int k, j, p, q, it, nsel = 0;
    /* c = ref + (mag - ref).mean(axis=0), ref the first selected row: summing raw values far from
     * the origin directly loses ~0.1 count in float; numpy reduces axis 0 row by row */
    for (k = 0; k < count; k++) {
        if (!selected(g, m, k))
            continue;
        if (nsel == 0)
            for (j = 0; j < 3; j++)
                ref[j] = g->raw[k][j];
        for (j = 0; j < 3; j++)
            c[j] += g->raw[k][j] - ref[j];
        nsel++;
    }
    if (nsel < 1)
        return 0;
    for (j = 0; j < 3; j++)
        c[j] = ref[j] + c[j] / (mkc_real)nsel;
    /* scale = sqrt(mean(sum((mag - c)^2, axis=1))) or 1.0 */
    for (k = 0, p = 0; k < count; k++) {
        mkc_real d0, d1, d2;
        if (!selected(g, m, k))
            continue;
        d0 = g->raw[k][0] - c[0];
        d1 = g->raw[k][1] - c[1];
        d2 = g->raw[k][2] - c[2];
        g->core.ebuf[p++] = d0 * d0 + d1 * d1 + d2 * d2;
    }
    scale = MKC_SQRT_R(mkc__pairwise_sum(g->core.ebuf, nsel) / (mkc_real)nsel);
    if (scale == RC(0.0))
        scale = RC(1.0);
    /* columns [2 m', 1], target |m'|^2: normal equations (lower triangle, first pass), then two
     * refinement passes x += N^-1 G^T (y - G x) */
    for (p = 0; p < 4; p++)
        for (q = 0; q < 4; q++)
            N[p][q] = CR(0.0);
    for (it = 0; it < MKC_SPHERE_PASSES; it++) {
#if MKC_CREAL_FLOAT
        sphere_pass(g, count, m, c, scale, xf, N, rhs, it == 0);
#else
        for (p = 0; p < 4; p++)
            rhs[p] = CR(0.0);
        for (k = 0; k < count; k++) {
            mkc_creal u[3], row[4], y, r;
            if (!selected(g, m, k))
                continue;
            for (j = 0; j < 3; j++)
                u[j] = (mkc_creal)((g->raw[k][j] - c[j]) / scale);
            row[0] = CR(2.0) * u[0];
            row[1] = CR(2.0) * u[1];
            row[2] = CR(2.0) * u[2];
            row[3] = CR(1.0);
            y = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
            r = y - (row[0] * x[0] + row[1] * x[1] + row[2] * x[2] + row[3] * x[3]);
            for (p = 0; p < 4; p++) {
                rhs[p] += row[p] * r;
                if (it == 0)
                    for (q = 0; q <= p; q++)
                        N[p][q] += row[p] * row[q];
            }
        }
#endif
        if (!chol4((const mkc_creal(*)[4])N, rhs, dx))
            return 0;
        for (p = 0; p < 4; p++) {
#if MKC_CREAL_FLOAT
            xf[p] = mkc__ff_add_f(xf[p], dx[p]);
            x[p] = xf[p].hi;
#else
            x[p] += dx[p];
#endif
        }
    }
    for (j = 0; j < 3; j++)
        bb[j] = (mkc_real)x[j];
    kk = (mkc_real)x[3];
    F2 = kk + (bb[0] * bb[0] + bb[1] * bb[1] + bb[2] * bb[2]);
    if (!(MKC_ISFINITE(F2) && F2 > RC(0.0)))
        return 0;
    for (j = 0; j < 3; j++)
        b_out[j] = c[j] + scale * bb[j];
    *F_out = scale * MKC_SQRT_R(F2);
    return 1;
}

mkc_real mkc__distance_mad(mkc_mag_t *g, int count, const mkc_real *c, mkc_real r, mkc_real *med)
{
    mkc_real *w = g->core.ebuf, m;
    int k;
    for (k = 0; k < count; k++)
        w[k] = mkc__raw_distance(g, k, c) - r;
    m = mkc__median(w, count);
    for (k = 0; k < count; k++)
        w[k] = MKC_FABS_R(mkc__raw_distance(g, k, c) - r - m);
    *med = m;
    return RC(MKC_MAD_SCALE) * mkc__median(w, count);
}

/* r_k = |m_k - centre| - F (recomputed, not stored); the selection |r_k - median| <= 3 * 1.4826 MAD
 * (all rows when the MAD is 0) into *s; returns how many rows it keeps. Scratch: g->core.ebuf. */
static int distance_selection(mkc_mag_t *g, int count, const mkc_real *centre, mkc_real F, sel *s)
{
    mkc_real med, mad = mkc__distance_mad(g, count, centre, F, &med), thr;
    int k, n = 0;
#define DIST_RES(k) (mkc__raw_distance(g, (k), centre) - F)
    s->use_mask = mad > RC(0.0);
    thr = RC(3.0) * mad;
    for (k = 0; k < (count + 31) / 32; k++)
        s->keep[k] = 0u;
    for (k = 0; k < count; k++) {
        int in = !s->use_mask || MKC_FABS_R(DIST_RES(k) - med) <= thr;
        s->keep[k >> 5] |= (uint32_t)in << (k & 31);
        n += in;
    }
#undef DIST_RES
    return n;
}

void mkc__axis_medians(mkc_mag_t *g, int count, mkc_real *med)
{
    mkc_real *w = g->core.ebuf;
    int j, k;
    for (j = 0; j < 3; j++) {
        for (k = 0; k < count; k++)
            w[k] = g->raw[k][j];
        med[j] = mkc__median(w, count);
    }
}

/* sphere_fit, then refit without the samples whose |m - b| - F exceeds 3 robust scales (bursts),
 * twice at most. The first fit already leaves out the samples whose distance to the coordinate-wise
 * median is more than 3 robust scales from the median distance (gross spikes). */
int mkc__robust_sphere_fit(mkc_mag_t *g, int count, mkc_real *b, mkc_real *F)
{
    sel all, first;
    int pass, nfirst;
    mkc_real cm[3];
    all.use_mask = 0;
    mkc__axis_medians(g, count, cm);
    nfirst = distance_selection(g, count, cm, RC(0.0), &first);
    if (!sphere_fit(g, count, (first.use_mask && nfirst >= 8) ? &first : &all, b, F))
        return 0;
    for (pass = 0; pass < 2; pass++) {
        sel keep;
        int nkeep = distance_selection(g, count, b, *F, &keep);
        if (nkeep < 8 || nkeep == count)
            return 1;
        if (!sphere_fit(g, count, &keep, b, F))
            return 0;
    }
    return 1;
}

/* sphere_coverage(raw[:count] - b): fraction of the 72 cells hit by the unit directions. */
mkc_real mkc__sphere_coverage_raw(const mkc_mag_t *g, int count, const mkc_real *b)
{
    int hit[MKC_N_CELLS], k;
    for (k = 0; k < MKC_N_CELLS; k++)
        hit[k] = 0;
    for (k = 0; k < count; k++) {
        mkc_real v0 = g->raw[k][0] - b[0], v1 = g->raw[k][1] - b[1], v2 = g->raw[k][2] - b[2];
        mkc_real nrm = MKC_SQRT_R(v0 * v0 + v1 * v1 + v2 * v2);
        if (nrm > RC(0.0))
            hit[mkc__unit_direction_cell(v0 / nrm, v1 / nrm, v2 / nrm)] = 1;
    }
    return mkc__coverage_of_unit_cells(hit, MKC_N_CELLS);
}

/* calib/ellipsoid.py sphere_theta: theta of eq. (36)-(37) for the sphere |m' - c| = r in the
 * features' coordinates, |m'|^2 - 2 c^T m' = k divided by k = r^2 - |c|^2; 0 when k <= 0. */
int mkc__sphere_theta(const mkc_creal *c, mkc_creal r, mkc_real *theta)
{
#if MKC_CREAL_FLOAT
    /* k and the quotients in float-float, rounded once: the cold start begins here */
    mkc_ff kf = {0.0f, 0.0f}, inv;
    int j;
    mkc__dot2_prod(&kf, r, r);
    for (j = 0; j < 3; j++)
        mkc__dot2_prod(&kf, -c[j], c[j]);
    kf = mkc__ff_make(kf.hi, kf.lo);
    if (!(isfinite(kf.hi) && kf.hi > 0.0f))
        return 0;
    inv = mkc__ff_div(mkc__ff_make(1.0f, 0.0f), kf);
    theta[0] = theta[1] = theta[2] = inv.hi;
    theta[3] = theta[4] = theta[5] = 0.0f;
    for (j = 0; j < 3; j++)
        theta[6 + j] = mkc__ff_mul_f(inv, -2.0f * c[j]).hi;
    return 1;
#else
    mkc_creal k = r * r - (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    if (!(MKC_ISFINITE(k) && k > CR(0.0)))
        return 0;
    theta[0] = (mkc_real)(CR(1.0) / k);
    theta[1] = (mkc_real)(CR(1.0) / k);
    theta[2] = (mkc_real)(CR(1.0) / k);
    theta[3] = theta[4] = theta[5] = RC(0.0);
    theta[6] = (mkc_real)(-CR(2.0) * c[0] / k);
    theta[7] = (mkc_real)(-CR(2.0) * c[1] / k);
    theta[8] = (mkc_real)(-CR(2.0) * c[2] / k);
    return 1;
#endif
}
