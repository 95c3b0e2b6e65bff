/* test_fmath.c: the all-float build's own cbrt and axis atan2 (src/fmath.c) against the host's libm.
 *
 * Built on the host with the all-float flags (-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0)
 * by tests/test_fmath.py. Prints "max_ulp_cbrt <value>" and exits 0 when every check holds:
 * cbrt within 1 ulp of the correctly rounded double cbrt over normal and subnormal arguments, and the
 * exact special values; atan2 at every signed zero and axis equal to the host's atan2f bit for bit.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "mkc_internal.h"

static int failures;

static uint32_t bits_of(float x)
{
    uint32_t u;
    memcpy(&u, &x, sizeof u);
    return u;
}

static void check(int ok, const char *what, double a, double b)
{
    if (!ok) {
        failures++;
        printf("FAIL %s: %.9g against %.9g\n", what, a, b);
    }
}

/* |got - ref| in units of the last place of ref rounded to float */
static double ulps(float got, double ref)
{
    float r = (float)ref;
    double ulp = (double)nextafterf(r, INFINITY) - (double)r;
    return fabs((double)got - ref) / ulp;
}

int main(void)
{
    double worst = 0.0;
    uint32_t s = 2463534242u;
    long i;
    const float zeros_and_axes[][2] = {{0.0f, 1.0f}, {-0.0f, 1.0f}, {0.0f, -1.0f}, {-0.0f, -1.0f},
                                       {0.0f, 0.0f}, {-0.0f, 0.0f}, {0.0f, -0.0f}, {-0.0f, -0.0f},
                                       {1.0f, 0.0f}, {1.0f, -0.0f}, {-1.0f, 0.0f}, {-1.0f, -0.0f},
                                       {3.5e-3f, 0.0f}, {-2.0e4f, -0.0f}, {0.0f, 7.0e-40f}, {-0.0f, -7.0e-40f}};
    for (i = 0; i < 2000000; i++) {
        float x, m;
        int e;
        s ^= s << 13; s ^= s >> 17; s ^= s << 5;                 /* xorshift32 */
        m = 1.0f + (float)(s >> 9) * (1.0f / 8388608.0f);        /* [1, 2) */
        e = (int)(s % 300u) - 160;                               /* subnormals to 2^139 */
        x = ldexpf(m, e);
        if (!(x > 0.0f) || isinf(x))
            continue;
        {
            double u = ulps(mkc__cbrtf(x), cbrt((double)x));
            if (u > worst)
                worst = u;
        }
    }
    check(worst <= 1.0, "cbrt within 1 ulp", worst, 1.0);
    check(mkc__cbrtf(27.0f) == 3.0f, "cbrt(27)", (double)mkc__cbrtf(27.0f), 3.0);
    check(mkc__cbrtf(0.0f) == 0.0f, "cbrt(0)", (double)mkc__cbrtf(0.0f), 0.0);
    check(isinf(mkc__cbrtf(INFINITY)), "cbrt(inf)", (double)mkc__cbrtf(INFINITY), (double)INFINITY);
    check(isnan(mkc__cbrtf(NAN)), "cbrt(nan)", (double)mkc__cbrtf(NAN), (double)NAN);
    for (i = 0; i < (long)(sizeof zeros_and_axes / sizeof zeros_and_axes[0]); i++) {
        float y = zeros_and_axes[i][0], x = zeros_and_axes[i][1];
        float got = mkc__atan2f_axes(y, x), ref = atan2f(y, x);
        check(bits_of(got) == bits_of(ref), "atan2 on an axis, bit for bit", (double)got, (double)ref);
    }
    printf("max_ulp_cbrt %.4f\n", worst);
    return failures != 0;
}
