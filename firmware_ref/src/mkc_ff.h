/* mkc_ff.h: float-float ("double-word") arithmetic for the all-float checkpoint code.
 *
 * A value is an unevaluated sum hi + lo of two floats with |lo| <= ulp(hi) / 2: 48 significant
 * bits from single-precision operations only. The checkpoint results that flow back into the
 * stream (the sphere fit that sets the normalisation and starts the cold start, the calibration
 * that re-centres it) are computed with their sums and residuals in float-float, so that rounding
 * them to float gives what the double build rounds them to (up to a tie within ~1e-13 relative).
 * The error-free transformations (Knuth's two-sum, Dekker's / an FMA two-product) are exact
 * under IEEE round-to-nearest without contraction (-ffp-contract=off).
 */
#ifndef MKC_FF_H
#define MKC_FF_H

#include <math.h>

typedef struct mkc_ff {
    float hi, lo;
} mkc_ff;

/* a handful of flops each: -Os calls those used in several places (the checkpoint code, where
 * flash counts more than a call) */
#define MKC_FF_INLINE static inline

/* s + e = a + b exactly (two-sum, any order of magnitude) */
MKC_FF_INLINE float mkc__two_sum_f(float a, float b, float *e)
{
    float s = a + b, bb = s - a;
    *e = (a - (s - bb)) + (b - bb);
    return s;
}

/* p + e = a b exactly: one FMA where the FPU has it (Cortex-M4F/M7/M33), Dekker's splitting else */
MKC_FF_INLINE float mkc__two_prod_f(float a, float b, float *e)
{
    float p = a * b;
#if defined(FP_FAST_FMAF) || defined(__FP_FAST_FMAF)
    *e = fmaf(a, b, -p);
#else
    const float split = 4097.0f;           /* 2^12 + 1: halves of 12 bits, whose products are exact */
    float ca = split * a, cb = split * b;
    float ah = ca - (ca - a), al = a - ah, bh = cb - (cb - b), bl = b - bh;
    *e = ((ah * bh - p) + ah * bl + al * bh) + al * bl;
#endif
    return p;
}

MKC_FF_INLINE mkc_ff mkc__ff_make(float hi, float lo)
{
    mkc_ff r;
    r.hi = mkc__two_sum_f(hi, lo, &r.lo);
    return r;
}

/* a + b (accurate to ~2^-46 relative unless they cancel to below that) */
MKC_FF_INLINE mkc_ff mkc__ff_add(mkc_ff a, mkc_ff b)
{
    float e, s = mkc__two_sum_f(a.hi, b.hi, &e);
    return mkc__ff_make(s, e + (a.lo + b.lo));
}

MKC_FF_INLINE mkc_ff mkc__ff_add_f(mkc_ff a, float b)
{
    float e, s = mkc__two_sum_f(a.hi, b, &e);
    return mkc__ff_make(s, e + a.lo);
}

/* a b for floats a, b: exact */
MKC_FF_INLINE mkc_ff mkc__ff_prod_f(float a, float b)
{
    mkc_ff r;
    r.hi = mkc__two_prod_f(a, b, &r.lo);
    return r;
}

/* a b for a float-float a and a float b */
MKC_FF_INLINE mkc_ff mkc__ff_mul_f(mkc_ff a, float b)
{
    float e, p = mkc__two_prod_f(a.hi, b, &e);
    return mkc__ff_make(p, e + a.lo * b);
}

/* a b for float-floats */
MKC_FF_INLINE mkc_ff mkc__ff_mul(mkc_ff a, mkc_ff b)
{
    float e, p = mkc__two_prod_f(a.hi, b.hi, &e);
    return mkc__ff_make(p, e + (a.hi * b.lo + a.lo * b.hi));
}

/* a / b for float-floats: q = a.hi / b.hi, then one correction by the exact remainder a - q b */
MKC_FF_INLINE mkc_ff mkc__ff_div(mkc_ff a, mkc_ff b)
{
    float q = a.hi / b.hi, e, p = mkc__two_prod_f(q, b.hi, &e);
    float r = (((a.hi - p) - e) + a.lo) - q * b.lo;
    return mkc__ff_make(q, r / b.hi);
}

/* sqrt(a) for a float-float a > 0: s = sqrtf(a.hi), then one Newton step with the exact a - s^2 */
MKC_FF_INLINE mkc_ff mkc__ff_sqrt(mkc_ff a)
{
    float s = sqrtf(a.hi), e, p = mkc__two_prod_f(s, s, &e);
    return mkc__ff_make(s, (((a.hi - p) - e) + a.lo) / (2.0f * s));
}

/* Cascaded summation (Ogita, Rump and Oishi's Sum2 / Dot2): acc.hi collects the rounded sum, acc.lo
 * the exact rounding errors of every step; hi + lo is the sum as if computed in twice the precision. */
MKC_FF_INLINE void mkc__dot2_add(mkc_ff *acc, float a)
{
    float q;
    acc->hi = mkc__two_sum_f(acc->hi, a, &q);
    acc->lo += q;
}

MKC_FF_INLINE void mkc__dot2_prod(mkc_ff *acc, float a, float b)
{
    float e, q, p = mkc__two_prod_f(a, b, &e);
    acc->hi = mkc__two_sum_f(acc->hi, p, &q);
    acc->lo += q + e;
}

#endif /* MKC_FF_H */
