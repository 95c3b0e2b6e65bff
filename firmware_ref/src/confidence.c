/* confidence.c: the streaming calibrator's switching test and the rest-cloud test of its sphere fit;
 * calib/confidence.py paired_gain / supports_switch and calib/quality.py sphere_spread.
 *
 * Scratch at a checkpoint, after the quality figures: core.ebuf holds the copies that medians
 * reorder and the compacted differences; both calibrations' relative residuals are recomputed where
 * used (the same operations, so the same bits).
 */
#include "mkc_internal.h"


/* m = S (raw_k - b); returns |m| (relative_residuals' y row and its norm) */
#define calibrated(g, k, c, m) mkc__calibrated_norm((g)->raw[(k)], (c)->hard_iron, (c)->soft_iron, (m))

/* supports_switch: 1 when the window supports replacing `acc` by `trial`, 2 when it does so strongly
 * (gain > Z_RESTART se, the pooled calibrator's restart test), 3 when strongly and `acc` fits the
 * trial's inliers DOMINANCE times worse in mean squared residual (residual_ratio: sum(e_a^2) >
 * DOMINANCE sum(e_t^2), sums in sample order; a wrong mode the pool must leave at once), 0 otherwise;
 * i.e. gain > z se with
 * D_k = e_a,k^2 - e_t,k^2 over the trial's inliers, e_k = |S (m_k - b)| / F - 1, gain = mean(D) and
 * se^2 = G / (G - 1) sum_c (sum_{k in c} (D_k - gain))^2 / n^2 clustered by the trial-calibrated
 * direction cell c (G occupied cells). */
int mkc__supports_switch(mkc_mag_t *g, int count, const mkc_mag_calibration *trial, const mkc_mag_calibration *acc)
{
    mkc_real *w = g->core.ebuf, m[3], med, mad, thr, gain, sa = RC(0.0), st = RC(0.0);
    mkc_creal sums[MKC_N_CELLS], ss = CR(0.0), se;
    int used[MKC_N_CELLS], k, n = 0, j, G = 0;
    uint32_t inlier[(MKC_W + 31) / 32];         /* IS_IN of each row, for the second pass */
#define EA(k) (calibrated(g, (k), acc, m) / acc->field - RC(1.0))
    /* the MAD of e_t (stats.c mkc__mad_about_median's steps). The first three passes fill w with
     * the trial's norms |m_cal| (mkc__calibrated_norms), then work in place. */
    mad = mkc__calibrated_mad(g, count, trial->hard_iron, (const mkc_real(*)[3])trial->soft_iron, trial->field,
                              RC(1.0), &med);
    thr = RC(MKC_OUTLIER_K) * mad;
#define IS_IN(et, ea) (!(mad != RC(0.0) && MKC_FABS_R((et) - med) > thr) && MKC_ISFINITE(et) && MKC_ISFINITE(ea))
    mkc__calibrated_norms(g, count, trial->hard_iron, (const mkc_real(*)[3])trial->soft_iron, w);
    for (k = 0; k < (count + 31) / 32; k++)
        inlier[k] = 0u;
    for (k = 0; k < count; k++) {
        mkc_real et = w[k] / trial->field - RC(1.0), ea = EA(k);
        if (IS_IN(et, ea)) {
            inlier[k >> 5] |= 1u << (k & 31);
            w[n++] = ea * ea - et * et;        /* compacted in place: n <= k */
            sa += ea * ea;                     /* residual_ratio's sums, in sample order */
            st += et * et;
        }
    }
    if (n < 2)
        return 0;
    gain = mkc__pairwise_sum(w, n) / (mkc_real)n;
    for (k = 0; k < MKC_N_CELLS; k++) {
        sums[k] = CR(0.0);
        used[k] = 0;
    }
    for (k = 0, j = 0; k < count; k++) {
        if (inlier[k >> 5] >> (k & 31) & 1u) {
            mkc_real mt[3], nk = calibrated(g, k, trial, mt);
            /* numpy: cal / max(|cal|, 1e-300), the zero vector's cell at |cal| = 0 */
            int c, i;
            for (i = 0; i < 3; i++)
                mt[i] = nk > RC(0.0) ? mt[i] / nk : RC(0.0);
            c = mkc__unit_direction_cell(mt[0], mt[1], mt[2]);
            sums[c] += (mkc_creal)(w[j++] - gain);
            used[c] = 1;
        }
    }
#undef IS_IN
#undef EA
    for (k = 0; k < MKC_N_CELLS; k++) {
        ss += sums[k] * sums[k];
        G += used[k];
    }
    if (G < 2)
        return 0;
    se = MKC_SQRT_C(ss * (mkc_creal)G / (mkc_creal)(G - 1)) / (mkc_creal)n;
    if ((mkc_creal)gain > CR(MKC_Z_RESTART) * se)
        return (st > RC(0.0) ? sa / st > RC(MKC_DOMINANCE) : sa > RC(0.0)) ? 3 : 2;
    return (mkc_creal)gain > CR(MKC_Z_SWITCH) * se;
}

/* sphere_spread: 1.4826 MAD of |m - c| - r over the window, relative to r (HUGE_VAL for r <= 0). */
mkc_real mkc__sphere_spread(mkc_mag_t *g, int count, const mkc_real *c, mkc_real r)
{
    mkc_real med;
    if (!(r > RC(0.0)) || count <= 0)
        return RC(HUGE_VAL);
    return mkc__distance_mad(g, count, c, r, &med) / r;
}
