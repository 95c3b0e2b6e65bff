/* stats.c: the numpy reductions the calibrator's checkpoint logic uses, reproduced exactly:
 * np.sum/np.mean (pairwise summation), np.median (selection; mean of the two middle values), and
 * the direction cells of unit vectors (calib/quality.py direction_cells).
 */
#include "mkc_internal.h"

/* numpy's pairwise summation (the add.reduce of a contiguous float64 array): blocks of <= 128
 * with 8 partial sums, split in halves (multiples of 8) above that. Same order, same result. */
mkc_real mkc__pairwise_sum(const mkc_real *x, int n)
{
    if (n < 8) {
        mkc_real res = RC(-0.0);
        int i;
        for (i = 0; i < n; i++)
            res += x[i];
        return res;
    } else if (n <= 128) {
        mkc_real r[8], res;
        int i, j;
        for (j = 0; j < 8; j++)
            r[j] = x[j];
        for (i = 8; i < n - (n % 8); i += 8)
            for (j = 0; j < 8; j++)
                r[j] += x[i + j];
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++)
            res += x[i];
        return res;
    } else {
        int n2 = n / 2;
        n2 -= n2 % 8;
        return mkc__pairwise_sum(x, n2) + mkc__pairwise_sum(x + n2, n - n2);
    }
}

/* k-th smallest of x[0..n-1] (x is reordered): Hoare's selection, median-of-three pivot. */
static mkc_real select_kth(mkc_real *x, int n, int k)
{
    int lo = 0, hi = n - 1;
    while (hi > lo) {
        int mid = lo + (hi - lo) / 2, i = lo, j = hi;
        mkc_real a = x[lo], b = x[mid], c = x[hi], pivot;
        /* median of three (no NaN reaches here: callers pass finite values) */
        if (a < b)
            pivot = b < c ? b : (a < c ? c : a);
        else
            pivot = a < c ? a : (b < c ? c : b);
        while (i <= j) {
            while (x[i] < pivot)
                i++;
            while (x[j] > pivot)
                j--;
            if (i <= j) {
                mkc_real t = x[i];
                x[i] = x[j];
                x[j] = t;
                i++;
                j--;
            }
        }
        if (k <= j)
            hi = j;
        else if (k >= i)
            lo = i;
        else
            return x[k];
    }
    return x[k];
}

/* np.median: the middle value, or the mean (a + b) / 2 of the two middle values for even n. */
mkc_real mkc__median(mkc_real *x, int n)
{
    mkc_real a, b;
    int i;
    if (n <= 0)
        return RC(NAN);
    if (n % 2)
        return select_kth(x, n, n / 2);
    a = select_kth(x, n, n / 2 - 1);
    /* after the selection x[n/2 .. n-1] >= a: the next order statistic is their minimum */
    b = x[n / 2];
    for (i = n / 2 + 1; i < n; i++)
        if (x[i] < b)
            b = x[i];
    return (a + b) / RC(2.0);
}

mkc_real mkc__mad_about_median(const mkc_real *x, int n, mkc_real *work, mkc_real *med)
{
    int k;
    for (k = 0; k < n; k++)
        work[k] = x[k];
    *med = mkc__median(work, n);
    for (k = 0; k < n; k++)
        work[k] = MKC_FABS_R(x[k] - *med);
    return RC(MKC_MAD_SCALE) * mkc__median(work, n);
}

#if MKC_SECTOR_BY_COMPARISON
/* The sector of (x, y), both non-zero, by comparisons instead of atan2: sector k holds the
 * longitudes atan2(y, x) in [-180 + 30 k, -150 + 30 k) degrees, so within each quadrant the two
 * boundaries are at 30 and 60 degrees from the x axis, i.e. where |y| = |x| / sqrt(3) and
 * |y| = sqrt(3) |x| (ties as the atan2 expression resolves them). As exact as atan2f (the comparisons
 * round at 1 ulp; a direction that close to a boundary is either side in float anyway), and a
 * tenth of its cost: the quality figures and the switching test take a cell per window sample. */
int mkc__sector_of(float x, float y)
{
    const float r3 = 1.7320508f;                 /* sqrt(3) */
    if (y > 0.0f) {
        if (x > 0.0f)
            return r3 * y < x ? 6 : (y < r3 * x ? 7 : 8);
        return r3 * y <= -x ? 11 : (y <= r3 * -x ? 10 : 9);
    }
    if (x > 0.0f)
        return r3 * -y <= x ? 5 : (-y <= r3 * x ? 4 : 3);
    return r3 * -y < -x ? 0 : (-y < r3 * -x ? 1 : 2);
}
#endif

/* Cell of a unit vector as calib/quality.py direction_cells computes it (on u = v / |v|). */
int mkc__unit_direction_cell(mkc_real ux, mkc_real uy, mkc_real uz)
{
    mkc_real z = mkc__min_r(mkc__max_r(uz, RC(-1.0)), RC(1.0));
    int band = (int)((z + RC(1.0)) * RC(0.5) * RC(MKC_N_BANDS)), sector;
#if MKC_SECTOR_BY_COMPARISON
    if (ux != RC(0.0) && uy != RC(0.0)) {
        sector = mkc__sector_of(ux, uy);
    } else
#endif
    {
        /* atan2 (in the all-float build only for a zero x or y: its signed zeros) */
        mkc_real lon = MKC_ATAN2_AXES_R(uy, ux) + RC(MKC_PI);
        sector = (int)(lon / (RC(2.0) * RC(MKC_PI)) * RC(MKC_N_SECTORS));
    }
    band = band < MKC_N_BANDS - 1 ? band : MKC_N_BANDS - 1;
    sector = sector < MKC_N_SECTORS - 1 ? sector : MKC_N_SECTORS - 1;
    return band * MKC_N_SECTORS + sector;
}

mkc_real mkc__coverage_of_unit_cells(const int *cells_hit, int ncells)
{
    int c, hit = 0;
    for (c = 0; c < ncells; c++)
        hit += cells_hit[c] != 0;
    return (mkc_real)hit / (mkc_real)ncells;
}
