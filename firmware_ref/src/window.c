/* window.c: streaming MKC-EM over a fixed-size window; kernels/window.py line by line.
 *
 * The window's weighted normal equations A theta = b (eq. (15)) are sums of per-row terms c x x^T
 * with c = w / d^2; each slot stores the c it added, so that replacing a sample subtracts exactly
 * what it added. theta is tracked every sample in O(n^2) by one refinement step with the last
 * equilibrated Cholesky factor; the factor is refreshed every `refactor` samples, at checkpoints
 * and when a step is not small. Every K samples the E-step (Algorithm 2) runs on the window's
 * residuals and A, b are rebuilt from the window with the new weights (fixed-point rounds of
 * Algorithm 1, eq. (16)), which also removes the add/remove rounding drift.
 *
 * Rows: a mkc_stream_t stores them (X, Y); a mkc_mag_t stores the raw 3-vectors and the rows are
 * the ellipsoid features of eq. (36)-(37) recomputed from them (target 1), bit-identical to the
 * stored features of the Python reference (same formula, same normalisation).
 *
 * Size: over 600 lines: the one estimator of kernels/window.py (per-sample tracking, rebuild,
 * E-step, restarts, cold starts), kept in one file so that it reads beside the reference.
 */
#include "mkc_internal.h"

/* x_k of eq. (36)-(37) for the normalised sample (m - c0) / s0 (kernels/magwindow.py). */
void mkc__ellipsoid_features(mkc_real mx, mkc_real my, mkc_real mz, const mkc_real *c0, mkc_real s0, mkc_real *xk)
{
    mkc_real x = (mx - c0[0]) / s0;
    mkc_real y = (my - c0[1]) / s0;
    mkc_real z = (mz - c0[2]) / s0;
    xk[0] = x * x;
    xk[1] = y * y;
    xk[2] = z * z;
    xk[3] = x * y;
    xk[4] = x * z;
    xk[5] = y * z;
    xk[6] = x;
    xk[7] = y;
    xk[8] = z;
}

/* Row i of slot s (file-local, so that it inlines into the loops below also in a shared object,
 * where the exported mkc__row could be interposed and so is called, not inlined). */
static const mkc_real *row_at(const mkc_core_t *c, int s, int i, mkc_real *buf)
{
    if (c->rows) {
        const mkc_mag_t *g = (const mkc_mag_t *)(const void *)c;
        mkc__ellipsoid_features(g->raw[s][0], g->raw[s][1], g->raw[s][2], g->c0, g->s0, buf);
        return buf;
    }
    return ((const mkc_stream_t *)(const void *)c)->X[s][i];
}

const mkc_real *mkc__row(const mkc_core_t *c, int s, int i, mkc_real *buf)
{
    return row_at(c, s, i, buf);
}

MKC_NOINLINE static mkc_real target(const mkc_core_t *c, int s, int i)
{
    if (c->rows)
        return RC(1.0);
    return ((const mkc_stream_t *)(const void *)c)->Y[s][i];
}

/* r = y - x^T theta, subtracting in ascending j (the reference's residual). */
MKC_NOINLINE static mkc_real residual_of(const mkc_real *x, mkc_real y, const mkc_real *theta, int n)
{
    int j;
    for (j = 0; j < n; j++)
        y -= x[j] * theta[j];
    return y;
}

/* The residual of row (s, i) at theta (buf: room for a recomputed magnetometer row). */
static mkc_real residual_at(const mkc_core_t *c, int s, int i, const mkc_real *theta, mkc_real *buf)
{
    return residual_of(row_at(c, s, i, buf), target(c, s, i), theta, c->cfg.n);
}

/* Write the new sample into slot s (before anything reads that slot's row). */
static void store_row(mkc_core_t *c, int s, const mkc_real *xk, const mkc_real *yk)
{
    int i, j, n = c->cfg.n, m = c->cfg.m;
    if (c->rows) {
        mkc_mag_t *g = (mkc_mag_t *)(void *)c;
        g->raw[s][0] = g->in_raw[0];
        g->raw[s][1] = g->in_raw[1];
        g->raw[s][2] = g->in_raw[2];
        return;
    }
    for (i = 0; i < m; i++) {
        mkc_stream_t *st = (mkc_stream_t *)(void *)c;
        st->Y[s][i] = yk[i];
        for (j = 0; j < n; j++)
            st->X[s][i][j] = xk[i * n + j];
    }
}

/* 1 / (2 d^2 sigma^2): w = exp(-e^2 * this) (kernels/correntropy.py weight_exponent_scale). */
static mkc_real weight_exponent_scale(mkc_real sigma, mkc_real d)
{
    return RC(1.0) / (RC(2.0) * d * d * sigma * sigma);
}

/* exp(-t) for t = e^2 / (2 d^2 sigma^2) >= 0 (kernels/correntropy.py gauss_weight): below t = 1e-3
 * h = 1 - omh with omh = t - t^2/2 + t^3/6 - t^4/24 + t^5/120 (normaliser.c omh_h), within an ulp
 * of exp(-t) and a few multiplies instead of a libm call (a wide kernel puts every weight there). */
static mkc_real gauss_weight(mkc_real t)
{
    if (t < RC(1e-3)) {
        mkc_real o = t * (RC(1.0) - t * (RC(0.5) - t * (RC(1.0 / 6.0) - t * (RC(1.0 / 24.0) - t * (RC(1.0 / 120.0))))));
        return RC(1.0) - o;
    }
    return MKC_EXP_R(-t);
}

/* A += c x x^T (lower triangle), b += c x y: one channel-row of eq. (15). */
static void row_update(mkc_acc A[MKC_N][MKC_N], mkc_acc *b, const mkc_real *x, mkc_real y, mkc_acc c, int n)
{
    int p, q;
    for (p = 0; p < n; p++) {
        mkc_acc xp = (mkc_acc)x[p] * c;
        b[p] += xp * (mkc_acc)y;
        for (q = 0; q <= p; q++)
            A[p][q] += xp * (mkc_acc)x[q];
    }
}

#if !MKC_ALL_FLOAT
/* Four consecutive channel-rows of eq. (15) in one pass over A, b: each element receives the four
 * terms in row order, exactly the additions of four row_update calls (same operations, same order,
 * same results), with one load and store of A per four rows instead of four. */
static void row_update4(mkc_acc A[MKC_N][MKC_N], mkc_acc *b, const mkc_real *const *x, const mkc_real *y,
                        const mkc_acc *c, int n)
{
    int p, q;
    const mkc_real *x0 = x[0], *x1 = x[1], *x2 = x[2], *x3 = x[3];
    for (p = 0; p < n; p++) {
        mkc_acc xp0 = (mkc_acc)x0[p] * c[0], xp1 = (mkc_acc)x1[p] * c[1];
        mkc_acc xp2 = (mkc_acc)x2[p] * c[2], xp3 = (mkc_acc)x3[p] * c[3];
        mkc_acc t = b[p];
        t += xp0 * (mkc_acc)y[0];
        t += xp1 * (mkc_acc)y[1];
        t += xp2 * (mkc_acc)y[2];
        t += xp3 * (mkc_acc)y[3];
        b[p] = t;
        /* two columns per step, written as two isomorphic statements so that the compiler may pair
         * them into one SIMD operation (element-wise: no reordering of any sum) */
        for (q = 0; q + 1 <= p; q += 2) {
            mkc_acc t0 = A[p][q], t1 = A[p][q + 1];
            t0 += xp0 * (mkc_acc)x0[q];
            t1 += xp0 * (mkc_acc)x0[q + 1];
            t0 += xp1 * (mkc_acc)x1[q];
            t1 += xp1 * (mkc_acc)x1[q + 1];
            t0 += xp2 * (mkc_acc)x2[q];
            t1 += xp2 * (mkc_acc)x2[q + 1];
            t0 += xp3 * (mkc_acc)x3[q];
            t1 += xp3 * (mkc_acc)x3[q + 1];
            A[p][q] = t0;
            A[p][q + 1] = t1;
        }
        if (q == p) {
            t = A[p][q];
            t += xp0 * (mkc_acc)x0[q];
            t += xp1 * (mkc_acc)x1[q];
            t += xp2 * (mkc_acc)x2[q];
            t += xp3 * (mkc_acc)x3[q];
            A[p][q] = t;
        }
    }
}
#endif

#if MKC_ALL_FLOAT
/* The all-float build's rebuild sums: A += c x x^T (lower triangle), b += c x y with each entry's
 * rounding carried in Kahan's compensation (Alo packed by rows, blo; the sum is entry - carry, folded
 * in by fold_carries), so each entry is within ~2 ulps of the exact sum of its rounded terms whatever
 * the window's length (Kahan 1965). Plain float sums of W rows err by up to ~W ulps of the terms'
 * size, and a window's off-diagonal moments nearly cancel; the double reference's calibration moves
 * by 10-130 times the relative error of A and b's entries, which left the all-float build's
 * free-running calibration on the last bits of libm, and blocks of 4 or 16 rows were not enough
 * (firmware_ref/README.md, "The float build"). */
static void row_update_compensated(mkc_acc A[MKC_N][MKC_N], mkc_acc *b, float *Alo, float *blo, const mkc_real *x,
                                   mkc_real y, mkc_acc c, int n)
{
    int p, q, k = 0;
    for (p = 0; p < n; p++) {
        float xp = x[p] * c;
        mkc__kahan_add_f(&b[p], &blo[p], xp * y);
        for (q = 0; q <= p; q++, k++)
            mkc__kahan_add_f(&A[p][q], &Alo[k], xp * x[q]);
    }
}

static void fold_carries(mkc_acc A[MKC_N][MKC_N], mkc_acc *b, const float *Alo, const float *blo, int n)
{
    int p, q, k = 0;
    for (p = 0; p < n; p++) {
        b[p] -= blo[p];
        for (q = 0; q <= p; q++, k++)
            A[p][q] -= Alo[k];
    }
}

#define MKC_N_LOWER (MKC_N * (MKC_N + 1) / 2)
#endif

/* Two consecutive channel-rows (the per-sample "- old row, + new row": row_update's additions for
 * row 0 then row 1, in that order per element) fused with the tracking step's residual sums over
 * the updated A: on return s[p] = b[p] - sum_q A[p][q] th[q] (A[p][q] below the diagonal, A[q][p]
 * above), each s[p] subtracting in ascending q as the reference's row loop does, so the step is
 * the same to the bit while A is read and written once. Rows are taken in pairs (p, p + 1), after
 * row 0 alone when n is odd: column q < p gives both rows' own terms and then column q's terms from
 * above the diagonal, which arrive in ascending row order after the ones row q itself left in s[q]. */
static void row_update2_residual(mkc_acc A[MKC_N][MKC_N], mkc_acc *b, const mkc_real x[2][MKC_N], mkc_real y0,
                                 mkc_acc c0, mkc_real y1, mkc_acc c1, int n, mkc_acc ts[2][MKC_N])
{
    /* x[0]: the old row, x[1]: the new one; ts[0]: theta, ts[1]: s (each pair one array, so that
     * the loop below walks three pointers) */
    const mkc_real *x0 = x[0], *x1 = x[1];
    const mkc_acc *th = ts[0];
    mkc_acc *s = ts[1];
    int p = 0, q;
    if (n & 1) {                                   /* row 0 alone: its diagonal only */
        mkc_acc u0 = (mkc_acc)x0[0] * c0, u1 = (mkc_acc)x1[0] * c1, t = b[0], a = A[0][0];
        t += u0 * (mkc_acc)y0;
        t += u1 * (mkc_acc)y1;
        b[0] = t;
        a += u0 * (mkc_acc)x0[0];
        a += u1 * (mkc_acc)x1[0];
        A[0][0] = a;
        s[0] = t - a * th[0];
        p = 1;
    }
    for (; p < n; p += 2) {
        mkc_acc(*Ap)[MKC_N] = A + p;
        mkc_acc u0 = (mkc_acc)x0[p] * c0, u1 = (mkc_acc)x1[p] * c1;              /* row p */
        mkc_acc v0 = (mkc_acc)x0[p + 1] * c0, v1 = (mkc_acc)x1[p + 1] * c1;      /* row p + 1 */
        mkc_acc th0 = th[p], th1 = th[p + 1], t0 = b[p], t1 = b[p + 1], a00, a10, a11;
        t0 += u0 * (mkc_acc)y0;
        t0 += u1 * (mkc_acc)y1;
        t1 += v0 * (mkc_acc)y0;
        t1 += v1 * (mkc_acc)y1;
        b[p] = t0;
        b[p + 1] = t1;
        q = 0;
        if (p > 0) do {   /* do-while: -Os keeps a for loop's test at the top, one more branch a pass */
            mkc_acc xq0 = (mkc_acc)x[0][q], xq1 = (mkc_acc)x[1][q], thq = ts[0][q], sq = ts[1][q];
            mkc_acc a0 = Ap[0][q], a1 = Ap[1][q];
            a0 += u0 * xq0;
            a0 += u1 * xq1;
            a1 += v0 * xq0;
            a1 += v1 * xq1;
            Ap[0][q] = a0;
            Ap[1][q] = a1;
            t0 -= a0 * thq;
            t1 -= a1 * thq;
            sq -= a0 * th0;
            sq -= a1 * th1;
            ts[1][q] = sq;
        } while (++q < p);
        a00 = Ap[0][p];                            /* q = p, p + 1 */
        a00 += u0 * (mkc_acc)x0[p];
        a00 += u1 * (mkc_acc)x1[p];
        a10 = Ap[1][p];
        a10 += v0 * (mkc_acc)x0[p];
        a10 += v1 * (mkc_acc)x1[p];
        a11 = Ap[1][p + 1];
        a11 += v0 * (mkc_acc)x0[p + 1];
        a11 += v1 * (mkc_acc)x1[p + 1];
        Ap[0][p] = a00;
        Ap[1][p] = a10;
        Ap[1][p + 1] = a11;
        t0 -= a00 * th0;
        t1 -= a10 * th0;
        t0 -= a10 * th1;                           /* row p's first term from above the diagonal */
        t1 -= a11 * th1;
        s[p] = t0;
        s[p + 1] = t1;
    }
}

/* A, b to zero before their sums, and the all-float build's carries lo[0 .. nlo - 1] (none: 0). */
static void clear_sums(mkc_core_t *c, float *lo, int nlo)
{
    int p, q, n = c->cfg.n;
    for (p = 0; p < n; p++) {
        c->b[p] = AC(0.0);
        for (q = 0; q < n; q++)
            c->A[p][q] = AC(0.0);
    }
    for (p = 0; p < nlo; p++)
        lo[p] = 0.0f;
}

/* Mirror A's lower triangle and solve A theta = b; theta is kept if A is singular. L, D then hold
 * the factor the tracking steps use (age 0), or are marked invalid. */
static int solve_window(mkc_core_t *c, mkc_acc *cond)
{
    int p, q, st, n = c->cfg.n;
    for (p = 0; p < n; p++)
        for (q = p + 1; q < n; q++)
            c->A[p][q] = c->A[q][p];
    st = mkc__spd_solve((const mkc_acc(*)[MKC_N])c->A, c->b, c->xs, c->L, c->D, n, cond);
    mkc__count(&c->counters.factors);
    if (st == MKC_OK) {
#if defined(__GNUC__) && MKC_ACC_IS_REAL
        __builtin_memcpy(c->theta, c->xs, (size_t)n * sizeof c->theta[0]);   /* not memmove: see mkc__rebuild */
#else
        for (p = 0; p < n; p++)
            c->theta[p] = (mkc_real)c->xs[p];
#endif
        c->counters.factor_age = 0;
    } else {
        c->counters.factor_age = -1;
    }
    return st;
}

/* One refinement step theta += (D L L^T D)^-1 (b - A theta) with the stored factor (O(n^2)); s:
 * b - A theta (row_update2_residual), overwritten. Returns 0 (theta untouched) if the step is not finite
 * or larger than REFINE_MAX_STEP |theta|: the factor is too stale, the caller refactors. */
static int refine_theta(mkc_core_t *c, mkc_acc *s)
{
    int p, k, i, j, n = c->cfg.n;
    mkc_acc step = AC(0.0), nan_sum = AC(0.0);
    const mkc_acc(*L)[MKC_N] = (const mkc_acc(*)[MKC_N])c->L, (*Lk)[MKC_N];
    /* forward solve L z = r, r = D (b - A theta): each s[p] is scaled by D[p], subtracts L[p][k] z_k
     * in ascending k and is then scaled by L[p][p] (the inverse pivot); backward solve L^T y = z:
     * each s[i] subtracts L[k][i] y_k in descending k and is then scaled by L[i][i], as the
     * reference. Row by row (the running sums in registers), two rows per pass sharing the loads
     * of z_k, y_k; a lone row first when n is odd (row 0 forward, row n - 1 backward). r, z and
     * then y overwrite s in place (the reference's xs). */
    p = 0;
    if (n & 1) {
        s[0] = s[0] * c->D[0] * L[0][0];
        p = 1;
    }
    for (; p < n; p += 2) {
        mkc_acc t0 = s[p] * c->D[p], t1 = s[p + 1] * c->D[p + 1];
        k = 0;
        if (p > 0) do {
            t0 -= L[p][k] * s[k];
            t1 -= L[p + 1][k] * s[k];
        } while (++k < p);
        t0 *= L[p][p];
        t1 -= L[p + 1][p] * t0;
        s[p] = t0;
        s[p + 1] = t1 * L[p + 1][p + 1];
    }
    i = n - 1;
    if (n & 1) {
        s[i] = s[i] * L[i][i];
        i -= 1;
    }
    for (; i > 0; i -= 2) {                        /* rows i, i - 1 */
        mkc_acc t0 = s[i], t1 = s[i - 1];
        k = n - 1;
        Lk = L + k;
        if (k > i) do {
            t0 -= (*Lk)[i] * s[k];
            t1 -= (*Lk)[i - 1] * s[k];
            Lk--;
        } while (--k > i);
        t0 *= L[i][i];
        t1 -= L[i][i - 1] * t0;
        s[i] = t0;
        s[i - 1] = t1 * L[i - 1][i - 1];
    }
    /* The reference's test: return 0 unless step <= REFINE_MAX_STEP size, step = max |xs_j| and
     * size = max |theta_j| as mkc__max_a gives them (a NaN wins, and fails the test). nan_sum, a
     * sum of the non-negative |values|, is NaN exactly when one of them is. Without a NaN, as the
     * rounded product x -> REFINE_MAX_STEP x is monotone, REFINE_MAX_STEP size is the largest of
     * the REFINE_MAX_STEP |theta_j|, so the test passes exactly when step <= REFINE_MAX_STEP
     * |theta_j| for some j, which the second loop looks for. */
    j = 0;
    do {                                           /* n >= 1 */
        mkc_acc xj = s[j] * c->D[j], ax = MKC_FABS_A(xj);
        c->xs[j] = xj;
        nan_sum += ax;
        nan_sum += (mkc_acc)MKC_FABS_R(c->theta[j]);
        if (ax > step)
            step = ax;
    } while (++j < n);
    if (nan_sum != nan_sum)
        return 0;
    for (j = 0; !(step <= AC(MKC_REFINE_MAX_STEP) * (mkc_acc)MKC_FABS_R(c->theta[j])); j++)
        if (j == n - 1)
            return 0;
    j = 0;
    do
        c->theta[j] = (mkc_real)((mkc_acc)c->theta[j] + c->xs[j]);
    while (++j < n);
    return 1;
}

/* Fixed-point rounds of Algorithm 1 on the window (eq. (16)), at most fp_rounds: weights at the
 * current theta -> A, b from scratch (C records each row's c) -> solve; stops when
 * ||theta_new - theta|| <= fp_tol ||theta||. */
int mkc__rebuild(mkc_core_t *c)
{
    int n = c->cfg.n, m = c->cfg.m;
    int count = (int)c->counters.count;
    int status = MKC_NOT_CONVERGED, rnd, s, i, j, st, k;
#if MKC_ALL_FLOAT
    /* each row is added with compensation as it comes (row_update_compensated); buf holds the
     * recomputed features of a magnetometer window */
    mkc_real buf[1][MKC_N];
    float Alo[MKC_N_LOWER + MKC_N], *blo = Alo + MKC_N_LOWER;     /* the carries of A, then of b */
#else
    /* up to four pending rows (c != 0) are added to A, b in one pass (row_update4); buf holds the
     * recomputed features of a magnetometer window, one buffer per pending row */
    mkc_real buf[4][MKC_N], py[4];
    const mkc_real *px[4];
    mkc_acc pc[4];
#endif
    for (rnd = 0; rnd < c->cfg.fp_rounds; rnd++) {
        mkc_acc wsum = AC(0.0), cond, num = AC(0.0), den = AC(0.0);
        /* theta copied with memcpy, which every firmware links: as a loop, GCC makes it a call to
         * memmove, which the library would be alone to need (0.25 KB) */
#if defined(__GNUC__)
        __builtin_memcpy(c->tprev, c->theta, (size_t)n * sizeof c->theta[0]);
#else
        for (j = 0; j < n; j++)
            c->tprev[j] = c->theta[j];
#endif
        k = 0;
#if MKC_ALL_FLOAT
        clear_sums(c, Alo, MKC_N_LOWER + MKC_N);
#else
        clear_sums(c, NULL, 0);
#endif
        if (c->defer_weights)
            c->defer_weights = 2;
        for (s = 0; s < count; s++) {
            for (i = 0; i < m; i++) {
                const mkc_real *x = row_at(c, s, i, buf[k]);
                mkc_real y = target(c, s, i);
                mkc_real r = residual_of(x, y, c->theta, n), w, cc;
                w = gauss_weight(r * r * weight_exponent_scale(c->sigma[i], c->d[i]));  /* exp(-r^2/(2 d^2 s^2)) */
                wsum += (mkc_acc)w;
                cc = w * (RC(1.0) / (c->d[i] * c->d[i]));
                if (!c->defer_weights)
                    c->C[s][i] = cc;
                if (cc != RC(0.0)) {
#if MKC_ALL_FLOAT
                    row_update_compensated(c->A, c->b, Alo, blo, x, y, (mkc_acc)cc, n);
#else
                    px[k] = x;
                    py[k] = y;
                    pc[k] = (mkc_acc)cc;
                    if (++k == 4) {
                        row_update4(c->A, c->b, px, py, pc, n);
                        k = 0;
                    }
#endif
                }
            }
        }
#if MKC_ALL_FLOAT
        fold_carries(c->A, c->b, Alo, blo, n);
#else
        for (j = 0; j < k; j++)           /* the last < 4 rows, in order */
            row_update(c->A, c->b, px[j], py[j], pc[j], n);
#endif
        if (wsum < (mkc_acc)n) {
            /* fewer effective equations than unknowns: the kernel lost the data (a bad theta) */
            c->counters.factor_age = -1;          /* L, D belong to an A that no longer exists */
            st = MKC_SINGULAR;
        } else {
            st = solve_window(c, &cond);
            c->fit.cond = (mkc_real)cond;
            mkc__count(&c->counters.fp_iters);
        }
        if (st != MKC_OK) {
            mkc__count(&c->counters.singular);
            return st;
        }
        for (j = 0; j < n; j++) {
            mkc_acc dj = (mkc_acc)c->theta[j] - (mkc_acc)c->tprev[j];
            mkc_acc tj = (mkc_acc)c->tprev[j];
            num += dj * dj;
            den += tj * tj;
        }
        if (MKC_SQRT_A(num) <= (mkc_acc)c->cfg.fp_tol * mkc__max_a(MKC_SQRT_A(den), AC(MKC_TINY_ACC))) {
            status = MKC_OK;
            break;
        }
    }
    return status;
}

/* The weight c = w / d^2 a rebuild round at theta records for row (s, i), with rebuild's operations. */
MKC_NOINLINE static mkc_real weight_at(const mkc_core_t *c, int s, int i, const mkc_real *theta, mkc_real sigma, mkc_real d)
{
    mkc_real buf[MKC_N];
    mkc_real r = residual_at(c, s, i, theta, buf), w;
    w = gauss_weight(r * r * weight_exponent_scale(sigma, d));  /* exp(-r^2/(2 d^2 s^2)) */
    return w * (RC(1.0) / (d * d));
}

void mkc__record_weights_at(mkc_core_t *c, const mkc_real *theta, const mkc_real *sigma, const mkc_real *d)
{
    int s, i;
    for (s = 0; s < MKC_W; s++)
        for (i = 0; i < MKC_M; i++)
            c->C[s][i] = RC(0.0);
    for (s = 0; s < (int)c->counters.count; s++)
        for (i = 0; i < c->cfg.m; i++)
            c->C[s][i] = weight_at(c, s, i, theta, sigma[i], d[i]);
}

int mkc__weights_recorded(const mkc_core_t *c)
{
    int s, i, count = (int)c->counters.count;
    for (s = 0; s < MKC_W; s++) {
        for (i = 0; i < MKC_M; i++) {
            int in = s < count && i < c->cfg.m;
            if (!(c->C[s][i] == (in ? weight_at(c, s, i, c->tprev, c->sigma[i], c->d[i]) : RC(0.0))))
                return 0;
        }
    }
    return 1;
}

/* Channel i's E-step starts from the default curvature (its inverse-Hessian warm start unknown). */
MKC_NOINLINE static void forget_curvature(mkc_core_t *c, int i)
{
    c->Hes[i][0] = EC(0.0);
    c->Hes[i][1] = EC(0.0);
    c->Hes[i][2] = EC(0.0);
}

/* Algorithm 2 per channel on the window's residuals at the current theta, warm-started. The
 * residuals r = y - x^T theta are formed where they are used (only their squares are kept, in
 * ebuf); the rebuild that follows recomputes them with the same operations, so the same bits. */
void mkc__estep_window(mkc_core_t *c)
{
    int n = c->cfg.n, m = c->cfg.m;
    int count = (int)c->counters.count;
    int s, i, j;
    mkc_ereal Fsum = EC(0.0);
    mkc_real buf[MKC_N], th[MKC_N];
    /* theta in a local copy: the stores to ebuf cannot alias it, so the loads need not wait for them */
    for (j = 0; j < n; j++)
        th[j] = c->theta[j];
    for (i = 0; i < m; i++) {
        mkc_real amax = RC(0.0), ymax = RC(0.0), ai;
        mkc_ereal s_new, d_new, F;
        int its, st;
        for (s = 0; s < count; s++) {
            mkc_real y = target(c, s, i), r = residual_at(c, s, i, th, buf);
            c->ebuf[s] = r * r;
            amax = mkc__max_r(amax, MKC_FABS_R(r));
            ymax = mkc__max_r(ymax, MKC_FABS_R(y));
        }
        ai = c->cfg.a > RC(0.0) ? c->cfg.a
                                              : mkc__max_r(c->cfg.a_factor * amax, RC(1e-12) * (RC(1.0) + ymax));
        if (!(RC(0.5) * c->a[i] <= ai && ai <= RC(2.0) * c->a[i])) {
            /* The truncation bound moved by more than 2x (a burst entered or left the window): the
             * curvature learnt in the old regime would throw the first step to the box edge.
             * Start this E-step from the default curvature. */
            forget_curvature(c, i);
            /* A burst entered (a grew): restart sigma on the robust side; in the Gaussian regime the
             * likelihood's slope is weaker than the prior's pull (estep.c), so it would never be seen */
            if (c->a[i] > RC(0.0) && ai > RC(2.0) * c->a[i] && c->sigma[i] > RC(MKC_START_SIGMA_ROBUST))
                c->sigma[i] = RC(MKC_START_SIGMA_ROBUST);
        }
        c->a[i] = ai;
        st = mkc__estep_channel(c->ebuf, count, (mkc_ereal)ai, (mkc_ereal)c->sigma[i], (mkc_ereal)c->d[i],
                                (mkc_ereal)c->cfg.sigma_lo, (mkc_ereal)c->cfg.sigma_hi,
                                (mkc_ereal)(c->cfg.d_lo * ai), (mkc_ereal)(c->cfg.d_hi * ai),
                                c->cfg.estep_max_iter, (mkc_ereal)c->cfg.estep_gtol,
                                (mkc_ereal)c->cfg.sigma_pull, c->Hes[i], &s_new,
                                &d_new, &F, &its);
        if (st == MKC_OK || st == MKC_NOT_CONVERGED) {
            c->sigma[i] = (mkc_real)s_new;
            c->d[i] = (mkc_real)d_new;
            Fsum += F;
        }
    }
    c->fit.last_objective = (mkc_real)Fsum;
    mkc__count(&c->counters.esteps);
}

/* kernels/window.py window_objective: the E-step objective (estep.c: the window's mean negative
 * log-likelihood of the truncated induced pdf, with the weak prior on sigma), summed over channels,
 * at the current theta, sigma, d and truncation a; the residuals formed as mkc__estep_window forms
 * them (their squares in ebuf). HUGE_VAL when sigma, d or a is not positive. */
mkc_ereal mkc__window_objective(mkc_core_t *c)
{
    int m = c->cfg.m;
    int count = (int)c->counters.count;
    int s, i;
    mkc_ereal total = EC(0.0), g0, g1;
    mkc_real buf[MKC_N];
    for (i = 0; i < m; i++) {
        if (!(c->sigma[i] > RC(0.0) && c->d[i] > RC(0.0) && c->a[i] > RC(0.0)) || count < 1)
            return EC(HUGE_VAL);
        for (s = 0; s < count; s++) {
            mkc_real r = residual_at(c, s, i, c->theta, buf);
            c->ebuf[s] = r * r;
        }
        total += mkc__estep_objective(MKC_LOG_E((mkc_ereal)c->sigma[i]), MKC_LOG_E((mkc_ereal)c->d[i]), c->ebuf,
                                      count, (mkc_ereal)c->a[i], (mkc_ereal)c->cfg.sigma_pull, &g0, &g1);
    }
    return total;
}

/* The mean square of channel i's residuals at theta, summed in mkc_acc; the residuals into ebuf. */
static mkc_acc mean_square_residual(mkc_core_t *c, int i)
{
    int s, count = (int)c->counters.count;
    mkc_real buf[MKC_N];
    mkc_acc acc = AC(0.0);
    for (s = 0; s < count; s++) {
        mkc_real r = residual_at(c, s, i, c->theta, buf);
        c->ebuf[s] = r;
        acc += (mkc_acc)r * (mkc_acc)r;
    }
    return acc / (mkc_acc)count;
}

/* First solve once min_samples are in: WLS (sigma = inf) on the window, then Algorithm 1. */
static int initialise_window(mkc_core_t *c)
{
    int n = c->cfg.n, m = c->cfg.m;
    int count = (int)c->counters.count;
    int s, i, st;
    mkc_acc cond;
    mkc_real buf[MKC_N];
#if MKC_ALL_FLOAT
    float Alo[MKC_N_LOWER + MKC_N], *blo = Alo + MKC_N_LOWER;     /* the carries of A, then of b */
    clear_sums(c, Alo, MKC_N_LOWER + MKC_N);
#else
    clear_sums(c, NULL, 0);
#endif
    for (s = 0; s < count; s++) {
        for (i = 0; i < m; i++) {
            mkc_real wd = c->d[i] > RC(0.0) ? RC(1.0) * (RC(1.0) / (c->d[i] * c->d[i])) : RC(1.0);
#if MKC_ALL_FLOAT
            row_update_compensated(c->A, c->b, Alo, blo, row_at(c, s, i, buf), target(c, s, i), (mkc_acc)wd, n);
#else
            row_update(c->A, c->b, row_at(c, s, i, buf), target(c, s, i), (mkc_acc)wd, n);
#endif
        }
    }
#if MKC_ALL_FLOAT
    fold_carries(c->A, c->b, Alo, blo, n);
#endif
    st = solve_window(c, &cond);
    c->fit.cond = (mkc_real)cond;
    if (st != MKC_OK) {
        mkc__count(&c->counters.singular);
        return st;
    }
    /* d unset (<= 0): start from the RMS of the WLS residuals; the first E-step refines it */
    for (i = 0; i < m; i++) {
        if (!(c->d[i] > RC(0.0)))
            c->d[i] = (mkc_real)mkc__max_a(MKC_SQRT_A(mean_square_residual(c, i)), AC(MKC_TINY_ACC));
    }
    return mkc__rebuild(c);
}

/* Forget sigma, d and theta and re-initialise from the window (WLS, then Algorithm 1). */
int mkc__restart(mkc_core_t *c)
{
    int i;
    mkc__count(&c->counters.restarts);
    for (i = 0; i < c->cfg.m; i++) {
        c->sigma[i] = c->cfg.sigma_start;
        c->d[i] = RC(-1.0);
        forget_curvature(c, i);
    }
    return initialise_window(c);
}

/* restart() from a given (high-breakdown) theta0 instead of WLS, as MM-estimation starts: sigma at
 * MKC_START_SIGMA_ROBUST, d at 1.4826 MAD of the residuals at theta0 (their RMS if the MAD is 0),
 * so the first M-step keeps the start's robustness. Scratch: c->ebuf. */
int mkc__restart_at(mkc_core_t *c, const mkc_real *theta0)
{
    int n = c->cfg.n, m = c->cfg.m;
    int count = (int)c->counters.count;
    int i, j, s;
    mkc__count(&c->counters.restarts);
    for (j = 0; j < n; j++)
        c->theta[j] = theta0[j];
    for (i = 0; i < m; i++) {
        mkc_acc ms;
        mkc_real med, mad;
        c->sigma[i] = RC(MKC_START_SIGMA_ROBUST);
        forget_curvature(c, i);
        ms = mean_square_residual(c, i);
        med = mkc__median(c->ebuf, count);
        for (s = 0; s < count; s++)
            c->ebuf[s] = (mkc_real)MKC_FABS_R(c->ebuf[s] - med);
        mad = RC(1.4826) * mkc__median(c->ebuf, count);
        c->d[i] = (mkc_real)mkc__max_a(mad > RC(0.0) ? (mkc_acc)mad : MKC_SQRT_A(ms), AC(MKC_TINY_ACC));
    }
    return mkc__rebuild(c);
}

/* em_rounds: `rounds` of Algorithm 3 on the window (E-step, then fixed-point rebuild) after a restart
 * whose status is st; stops at the first failure. */
static int em_rounds(mkc_core_t *c, int rounds, int st)
{
    int r;
    for (r = 0; r < rounds; r++) {
        if (st != MKC_OK && st != MKC_NOT_CONVERGED)
            return st;
        mkc__estep_window(c);
        st = mkc__rebuild(c);
    }
    return st;
}

/* mkc__cold_start from mkc__restart_at(theta0) instead of WLS. */
int mkc__cold_start_at(mkc_core_t *c, int rounds, const mkc_real *theta0)
{
    return em_rounds(c, rounds, mkc__restart_at(c, theta0));
}

/* Batch MKC-EM (Algorithm 3) on the window from scratch: restart() (WLS, then Algorithm 1 at the
 * start bandwidth), then `rounds` E-step + fixed-point rounds. Returns the last status. */
int mkc__cold_start(mkc_core_t *c, int rounds)
{
    return em_rounds(c, rounds, mkc__restart(c));
}

/* Feed one sample (xk: m x n row-major, yk: m) into window slot `slot` (-1: the ring buffer's
 * head). Returns MKC_OK, MKC_NOT_CONVERGED, MKC_SINGULAR, MKC_WARMING_UP or MKC_REJECTED. The
 * caller has checked the sample (finite, bounded). */
int mkc__learn_one(mkc_core_t *c, const mkc_real *xk, const mkc_real *yk, int slot)
{
    int n = c->cfg.n, m = c->cfg.m, W = c->cfg.window;
    int i, j, ready, st, old = 0, new_row = 0;
    /* rows: the old row, then the new one, for row_update2_residual; ts: theta, then b - A theta */
    mkc_real buf[MKC_N], rows[2][MKC_N], oy = RC(0.0), ny = RC(0.0);
    mkc_acc cond, ts[2][MKC_N], oc = -AC(0.0), nc = -AC(0.0);
    if (slot < 0) {
        slot = (int)c->counters.head;
        c->counters.head = (slot + 1) % W;
    }
    c->counters.last_slot = slot;
    if (slot < c->counters.count) {
        /* replace: subtract exactly what this slot added. One channel (m = 1): keep the old row
         * (store_row overwrites it) and subtract it in the same pass over A, b as the new row's
         * addition below (row_update2_residual: each element still receives "- old, + new" in that
         * order). A magnetometer row is computed straight into rows[0]. */
        if (m == 1 && c->C[slot][0] != RC(0.0)) {
            const mkc_real *xo = row_at(c, slot, 0, rows[0]);
            if (xo != rows[0])
                for (j = 0; j < n; j++)
                    rows[0][j] = xo[j];
            oy = target(c, slot, 0);
            oc = -(mkc_acc)c->C[slot][0];
            old = 1;
        } else if (m > 1) {
            for (i = 0; i < m; i++)
                if (c->C[slot][i] != RC(0.0))
                    row_update(c->A, c->b, row_at(c, slot, i, buf), target(c, slot, i), -(mkc_acc)c->C[slot][i],
                               n);
        }
    } else {
        mkc__count(&c->counters.count);                /* only while the window fills */
    }
    ready = c->counters.esteps > 0 || c->counters.fp_iters > 0;
    store_row(c, slot, xk, yk);
    for (i = 0; i < m; i++) {
        mkc_real r = yk[i], cc;
        for (j = 0; j < n; j++)
            r -= xk[i * n + j] * c->theta[j];
        cc = ready ? gauss_weight(r * r * weight_exponent_scale(c->sigma[i], c->d[i])) * (RC(1.0) / (c->d[i] * c->d[i]))
                   : RC(0.0);
        c->C[slot][i] = cc;
        if (cc != RC(0.0)) {
            if (m == 1) {
                ny = yk[0];
                nc = (mkc_acc)cc;
                new_row = 1;
            } else {
                row_update(c->A, c->b, xk + i * n, yk[i], (mkc_acc)cc, n);
            }
        }
    }
    /* A row that adds nothing (none replaced, weight 0, or m > 1, whose rows were added above)
     * enters row_update2_residual as 0 with weight -0: each of its terms is then -0, and
     * x + (-0) = x exactly for every x (+-0 included), so A and b are those of the updates above
     * and the pass still forms the residual the tracking step takes. */
    for (j = 0; j < n; j++) {
        rows[1][j] = xk[j];
        ts[0][j] = (mkc_acc)c->theta[j];
    }
    if (!old)
        for (j = 0; j < n; j++)
            rows[0][j] = RC(0.0);
    if (!new_row)
        for (j = 0; j < n; j++)
            rows[1][j] = RC(0.0);
    row_update2_residual(c->A, c->b, (const mkc_real(*)[MKC_N])rows, oy, oc, ny, nc, n, ts);
    c->counters.seen += 1;
    c->counters.since += 1;
    if (c->counters.count < c->cfg.min_samples) {
        st = MKC_WARMING_UP;
        goto done;
    }
    if (!ready) {
        st = initialise_window(c);
        if (st != MKC_OK && st != MKC_NOT_CONVERGED)
            goto done;
        c->counters.since = c->cfg.estep_every;        /* run the first E-step now */
    }
    if (c->counters.since >= c->cfg.estep_every) {
        c->counters.since = 0;
        mkc__estep_window(c);
        st = mkc__rebuild(c);
        if (st != MKC_OK && st != MKC_NOT_CONVERGED) {
            /* Recovery: restart Algorithm 3 on the window from WLS and the start bandwidth, so a
             * stream never stays stuck on a degenerate estimate (its weights would all be ~0). */
            st = mkc__restart(c);
        }
    } else {
        int64_t age = c->counters.factor_age;
        st = MKC_OK;
        if (age >= 0 && age < c->cfg.refactor_every && refine_theta(c, ts[1])) {
            c->counters.factor_age = age + 1;
        } else {
            st = solve_window(c, &cond);
            c->fit.cond = (mkc_real)cond;
            if (st != MKC_OK)
                mkc__count(&c->counters.singular);
        }
    }
done:                                                  /* every exit records its status */
    c->counters.status = st;
    return st;
}

/* ---- initialisation (state.py StreamConfig / allocate) ---- */


int mkc__core_init(mkc_core_t *c, const mkc_config *cfg, const mkc_real *sigma0, const mkc_real *d0,
                   const mkc_real *theta0, int rows)
{
    int i, n = cfg->n, m = cfg->m, W = cfg->window, K = cfg->estep_every, need, refactor;
    unsigned char *p = (unsigned char *)c;
    size_t k;
    /* the real settings as the state holds them (mkc_real), checked after that rounding: in a float
     * build a setting that rounds to 0 or inf is refused, and no double arithmetic is needed */
    mkc_core_cfg r;
    r.sigma_lo = (mkc_real)cfg->sigma_lo;
    r.sigma_hi = (mkc_real)cfg->sigma_hi;
    r.d_lo = (mkc_real)cfg->d_lo;
    r.d_hi = (mkc_real)cfg->d_hi;
    r.a_factor = (mkc_real)cfg->a_factor;
    r.a = (mkc_real)cfg->a;
    r.estep_gtol = (mkc_real)cfg->estep_gtol;
    r.fp_tol = (mkc_real)cfg->fp_tol;
    r.sigma_start = (mkc_real)cfg->sigma_start;
    r.sigma_pull = (mkc_real)cfg->sigma_pull;
    if (n < 1 || m < 1 || n > MKC_N || m > MKC_M || W > MKC_W || W < (n > 2 ? n : 2) || K < 1 ||
        cfg->fp_rounds < 0 || cfg->estep_max_iter < 0 || cfg->refactor_every < 0 || cfg->min_samples < 0)
        return MKC_BAD_INPUT;
    if (!(r.sigma_lo > RC(0.0) && r.sigma_lo < r.sigma_hi) || !(r.d_lo > RC(0.0) && r.d_lo < r.d_hi) ||
        !(r.a_factor > RC(0.0)) || !MKC_ISFINITE(r.a) || !(r.estep_gtol >= RC(0.0)) || !(r.fp_tol >= RC(0.0)) ||
        !(r.sigma_start > RC(0.0)) || !MKC_ISFINITE(r.sigma_hi) || !MKC_ISFINITE(r.d_hi) || !MKC_ISFINITE(r.sigma_start) ||
        !(r.sigma_pull >= RC(0.0)) || !MKC_ISFINITE(r.sigma_pull))
        return MKC_BAD_INPUT;
    for (i = 0; i < m; i++) {
        if (sigma0 && !(sigma0[i] > RC(0.0) && MKC_ISFINITE(sigma0[i])))
            return MKC_BAD_INPUT;
        if (d0 && !(d0[i] > RC(0.0) && MKC_ISFINITE(d0[i])))
            return MKC_BAD_INPUT;
    }
    if (theta0)
        for (i = 0; i < n; i++)
            if (!MKC_ISFINITE(theta0[i]))
                return MKC_BAD_INPUT;
    for (k = 0; k < sizeof(mkc_core_t); k++)       /* all zero, as numpy.zeros */
        p[k] = 0;
    if (cfg->min_samples > 0) {
        need = cfg->min_samples < W ? cfg->min_samples : W;
    } else {
        int eq = 2 * n > n + 8 ? 2 * n : n + 8;
        need = (eq + m - 1) / m;                      /* ceil: equations, not samples */
        need = need < W ? need : W;
    }
    if (cfg->refactor_every > 0) {
        refactor = cfg->refactor_every;
    } else {
        int w8 = W / 8 > 1 ? W / 8 : 1;
        refactor = K < w8 ? K : w8;
    }
    r.n = n;
    r.m = m;
    r.window = W;
    r.estep_every = K;
    r.fp_rounds = cfg->fp_rounds;
    r.estep_max_iter = cfg->estep_max_iter;
    r.min_samples = need;
    r.refactor_every = refactor;
    c->cfg = r;
    c->rows = rows;
    for (i = 0; i < m; i++) {
        c->sigma[i] = sigma0 ? sigma0[i] : RC(MKC_DEF_SIGMA0);
        c->d[i] = d0 ? d0[i] : RC(-1.0);
    }
    if (theta0)
        for (i = 0; i < n; i++)
            c->theta[i] = theta0[i];
    c->counters.status = MKC_WARMING_UP;
    c->fit.cond = RC(HUGE_VAL);
    return MKC_OK;
}
