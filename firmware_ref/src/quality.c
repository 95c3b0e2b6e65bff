/* quality.c: quality figures and the acceptance predicate of a trial calibration;
 * calib/quality.py quality_figures, calib/fit.py weighted_condition, calib/acceptance.py check.
 *
 * Scratch at a checkpoint (the E-step and rebuild are done): core.ebuf, the one window-sized
 * array, holds the copies that medians reorder and the compacted arrays numpy's means sum
 * (pairwise, in array order); the norms |m_cal| and residuals |m_cal| - F are recomputed from raw
 * where needed (the same operations, so the same bits), not stored.
 */
#include "mkc_internal.h"

mkc_real mkc__calibrated_mad(mkc_mag_t *g, int count, const mkc_real *b, const mkc_real S[3][3], mkc_real div,
                             mkc_real sub, mkc_real *med)
{
    mkc_real *w = g->core.ebuf, m;
    int k;
    mkc__calibrated_norms(g, count, b, S, w);
    for (k = 0; k < count; k++)
        w[k] = w[k] / div - sub;
    m = mkc__median(w, count);
    mkc__calibrated_norms(g, count, b, S, w);
    for (k = 0; k < count; k++)
        w[k] = MKC_FABS_R((w[k] / div - sub) - m);
    *med = m;
    return RC(MKC_MAD_SCALE) * mkc__median(w, count);
}

/* sqrt(mean(x[0..n-1])), the mean numpy's (pairwise) */
MKC_NOINLINE static mkc_real root_mean(const mkc_real *x, int n)
{
    return MKC_SQRT_R(mkc__pairwise_sum(x, n) / (mkc_real)n);
}

/* np.std of x[0..n-1] (work: n scratch values, may be x itself): sqrt(mean((x - mean(x))^2)). */
static mkc_real np_std(const mkc_real *x, int n, mkc_real *work)
{
    mkc_real mean = mkc__pairwise_sum(x, n) / (mkc_real)n;
    int k;
    for (k = 0; k < n; k++) {
        mkc_real d = x[k] - mean;
        work[k] = d * d;
    }
    return root_mean(work, n);
}

void mkc__quality_figures(mkc_mag_t *g, int count, const mkc_real *b, const mkc_real S[3][3], mkc_real F,
                          mkc_real condition, mkc_real *q)
{
    mkc_real *w = g->core.ebuf;
    mkc_real med, mad, thr;
    int hit[MKC_N_CELLS], k, nin = 0, nout = 0;
    for (k = 0; k < MKC_N_CELLS; k++)
        hit[k] = 0;
    /* m_cal = (raw - b) S^T; cells of m_cal / |m_cal|; residuals r = |m_cal| - F */
    for (k = 0; k < count; k++) {
        mkc_real m[3], nk = mkc__calibrated_norm(g->raw[k], b, S, m);
        if (nk > RC(0.0))
            hit[mkc__unit_direction_cell(m[0] / nk, m[1] / nk, m[2] / nk)] = 1;
    }
    /* outlier_mask: |r - median| > 3.5 * 1.4826 MAD (stats.c mkc__mad_about_median's steps). Each
     * pass below first fills w with the norms |m_cal| (mkc__calibrated_norms), then works in place. */
    mad = mkc__calibrated_mad(g, count, b, S, RC(1.0), F, &med);      /* r = |m_cal| / 1 - F, exactly */
    thr = RC(MKC_OUTLIER_K) * mad;
#define IS_OUT(r) (mad != RC(0.0) && MKC_FABS_R((r) - med) > thr)
    /* residual_rms: over the inliers (compacted in place: nin <= k) */
    mkc__calibrated_norms(g, count, b, S, w);
    for (k = 0; k < count; k++) {
        mkc_real r = w[k] - F;
        if (IS_OUT(r)) {
            nout++;
        } else {
            w[nin++] = r * r;
        }
    }
    /* (nin >= count / 2 always: at least half the residuals lie within one MAD of the median) */
    q[MKC_Q_RESIDUAL_RMS] = nin ? root_mean(w, nin) : RC(HUGE_VAL);
    mkc__calibrated_norms(g, count, b, S, w);
    for (k = 0; k < count; k++) {
        mkc_real r = w[k] - F;
        w[k] = r * r;
    }
    q[MKC_Q_RESIDUAL_RMS_ALL] = root_mean(w, count);
    /* np.std of the norms, then of the inliers' norms (compacted), each in w (np_std works in place) */
    mkc__calibrated_norms(g, count, b, S, w);
    q[MKC_Q_NORM_SPREAD] = np_std(w, count, w) / F;
    {
        int j = 0;
        mkc__calibrated_norms(g, count, b, S, w);
        for (k = 0; k < count; k++) {
            mkc_real nk = w[k];                    /* compacted in place: j <= k */
            if (!IS_OUT(nk - F))
                w[j++] = nk;
        }
        q[MKC_Q_NORM_SPREAD_INLIERS] = nin ? np_std(w, nin, w) / F : RC(HUGE_VAL);
    }
#undef IS_OUT
    q[MKC_Q_COVERAGE] = mkc__coverage_of_unit_cells(hit, MKC_N_CELLS);
    q[MKC_Q_OUTLIER_FRACTION] = (mkc_real)nout / (mkc_real)count;
    q[MKC_Q_CONDITION] = condition;
}

/* cond of the Jacobi-equilibrated weighted normal matrix sum_k w_k x_k x_k^T of the window, with
 * w = c d^2 the kernel weights (calib/fit.py weighted_condition); eigenvalues by cyclic Jacobi
 * (numpy: the 2-norm condition by SVD, the same number for this symmetric matrix). */
mkc_real mkc__weighted_condition(mkc_mag_t *g, int count)
{
    mkc_creal G[9][9], lam[9], dg[9], lo, hi;
    int p, q, n = 9;
#if MKC_CREAL_FLOAT
    /* The window's normal matrix A = sum_k c_k x_k x_k^T (eq. 15), which every checkpoint finds
     * rebuilt with the current weights c = w / d^2 (window.c mkc__rebuild, restart, cold start), is
     * that matrix divided by d^2: the same once equilibrated, without a pass over the window
     * (~1e5 instructions on a Cortex-M4F at W = 256); the figure differs by float rounding (~1e-6). */
    (void)count;
    for (p = 0; p < n; p++)
        for (q = 0; q <= p; q++)
            G[p][q] = (mkc_creal)g->core.A[p][q];
#else
    mkc_real xk[MKC_N];
    int k;
    mkc_real d = g->core.d[0];
    for (p = 0; p < n; p++)
        for (q = 0; q < n; q++)
            G[p][q] = CR(0.0);
    for (k = 0; k < count; k++) {
        mkc_real wk = g->core.C[k][0] * d * d;
        mkc_creal sw = MKC_SQRT_C((mkc_creal)mkc__max_r(wk, RC(0.0)));
        const mkc_real *x = mkc__row(&g->core, k, 0, xk);
        mkc_creal xw[9];
        for (p = 0; p < n; p++)
            xw[p] = (mkc_creal)x[p] * sw;
        for (p = 0; p < n; p++)
            for (q = 0; q <= p; q++)
                G[p][q] += xw[p] * xw[q];
    }
#endif
    for (p = 0; p < n; p++) {
        dg[p] = MKC_SQRT_C(G[p][p]);
        if (dg[p] == CR(0.0))
            return RC(HUGE_VAL);
    }
    for (p = 0; p < n; p++)
        for (q = 0; q <= p; q++)
            G[p][q] = G[q][p] = G[p][q] / (dg[p] * dg[q]);
    mkc__jacobi_eigen(G, n, lam, NULL);
    lo = CR(HUGE_VAL);
    hi = CR(0.0);
    for (p = 0; p < n; p++) {
        mkc_creal a = MKC_FABS_C(lam[p]);
        lo = a < lo ? a : lo;
        hi = a > hi ? a : hi;
    }
    if (!(lo > CR(0.0)))
        return RC(HUGE_VAL);
    return (mkc_real)(hi / lo);
}

/* AcceptanceRules.check: the failed criteria as bits (0: accepted); reason->v = coverage,
 * condition, outlier fraction, residual / field, field, disagreement. */
uint32_t mkc__acceptance_check(const mkc_mag_t *g, const mkc_real *q, mkc_real field, mkc_creal disagreement,
                               mkc_mag_reason *reason)
{
    const mkc_mag_rules *R = &g->rules;
    uint32_t fails = 0;
    mkc_real cov = q[MKC_Q_COVERAGE], cond = q[MKC_Q_CONDITION], out = q[MKC_Q_OUTLIER_FRACTION];
    mkc_real rel = field > RC(0.0) ? q[MKC_Q_RESIDUAL_RMS] / field : RC(HUGE_VAL);
    if (!(cov >= R->min_coverage))
        fails |= MKC_FAIL_COVERAGE;
    if (!(cond <= R->max_condition))
        fails |= MKC_FAIL_CONDITION;
    if (!(out <= R->max_outlier_fraction))
        fails |= MKC_FAIL_OUTLIERS;
    if (!(rel <= R->max_residual_rel))
        fails |= MKC_FAIL_RESIDUAL;
    if (g->unit_ut) {
        if (!(R->field_lo_ut <= field && field <= R->field_hi_ut))
            fails |= MKC_FAIL_FIELD_RANGE;
    } else if (!(MKC_ISFINITE(field) && field > RC(0.0))) {
        fails |= MKC_FAIL_FIELD_NONPOSITIVE;
    }
    if (disagreement >= CR(0.0) && !(disagreement <= (mkc_creal)R->max_disagreement_rel * MKC_FABS_C((mkc_creal)field)))
        fails |= MKC_FAIL_DISAGREEMENT;
    reason->code = fails ? MKC_REASON_REJECTED : MKC_REASON_NONE;
    reason->fails = fails;
    reason->v[0] = MKC_REASON_VALUE(cov);
    reason->v[1] = MKC_REASON_VALUE(cond);
    reason->v[2] = MKC_REASON_VALUE(out);
    reason->v[3] = MKC_REASON_VALUE(rel);
    reason->v[4] = MKC_REASON_VALUE(field);
    reason->v[5] = MKC_REASON_VALUE(disagreement);
    return fails;
}
