/* fmath.c: the all-float build's own cube root and axis atan2 (MKC_ALL_FLOAT only).
 *
 * cbrt gives the calibration's F; atan2 is asked only where x or y is zero (a direction cell's
 * sector; the other sectors are taken by comparisons, stats.c mkc__sector_of). Together they replace
 * about 1 KB of newlib (cbrtf, atan2f with atanf) in a firmware. cbrt is within 1 ulp and the axis
 * values are exact (tests/test_fmath.c), and the free-running calibrations stay within 1e-4 of the
 * double reference on every golden vector (tools/measure_float_precision.py). exp, log, expm1 and
 * log1p stay libm's: see firmware_ref/README.md, "The float build", for why.
 */
#include "mkc_internal.h"

#if MKC_ALL_FLOAT

/* cbrt(x) for x > 0: a first guess from the bits divided by 3 (the exponent field of x is 127 + e, that
 * of cbrt(x) 127 + e / 3, so bits / 3 + (2/3) 127 2^23 = bits / 3 + 0x2a555555 is cbrt(x) within 8%),
 * then Newton's step y <- y - (y^3 - x) / (3 y^2) four times (the error about squares: 8% -> 7e-3
 * -> 5e-5 -> 3e-9 -> float's rounding). */
float mkc__cbrtf(float x)
{
    union { float f; uint32_t u; } v;
    float y, scale = 1.0f;
    int i;
    if (!(x > 0.0f) || x > 3.40282347e38f)
        return x;                                            /* 0, negative (not passed), inf, NaN */
    if (x < 1.17549435e-38f) {                               /* subnormal: cbrt(x 2^24) / 2^8 */
        x *= 16777216.0f;
        scale = 1.0f / 256.0f;
    }
    v.f = x;
    v.u = v.u / 3u + 0x2a555555u;
    y = v.f;
    for (i = 0; i < 4; i++)
        y = y - (y * y * y - x) / (3.0f * y * y);
    return y * scale;
}

/* atan2(y, x) where x or y is zero (either sign), as C99 annex F defines it, rounded to float: the
 * callers take a cell's sector by comparisons (mkc__sector_of) when both are non-zero. */
float mkc__atan2f_axes(float y, float x)
{
    const float pi = 3.14159265f, half_pi = 1.57079633f;
    if (y == 0.0f) {
        if (x < 0.0f || (x == 0.0f && signbit(x)))
            return signbit(y) ? -pi : pi;
        return y;                                            /* +-0 */
    }
    return y > 0.0f ? half_pi : -half_pi;
}

#else
typedef int mkc__fmath_unused; /* ISO C: a translation unit needs a declaration */
#endif /* MKC_ALL_FLOAT */
