/* mkc_math.h: the libm calls of the library, spelled with the precision of their argument's type.
 *
 * The library mixes three arithmetic types whose precision is chosen at compile time (mkc_config.h):
 * mkc_real (storage), mkc_acc (normal equations) and mkc_ereal (E-step). Each call names its type
 * by suffix: MKC_SQRT_R(x) takes and returns mkc_real, MKC_EXP_E(x) mkc_ereal, MKC_FABS_A(x) mkc_acc;
 * calls on a plain double use the double function (sqrt, fabs, pow) directly. They map to the C99
 * <math.h> double functions or their f-suffixed float versions, so the library needs no <tgmath.h>
 * (newlib has no long double complex functions for it) and a float build never calls a double
 * function (on a single-precision FPU that is a software library call).
 */
#ifndef MKC_MATH_H
#define MKC_MATH_H

#include <math.h>

#include "mkc_config.h"

/* the function `name` in double (D) or float (F) */
#define MKC__FN_D(name) name
#define MKC__FN_F(name) name##f

#ifdef MKC_USE_FLOAT
#define MKC__FN_R MKC__FN_F
#else
#define MKC__FN_R MKC__FN_D
#endif
#if MKC_ACC_DOUBLE
#define MKC__FN_A MKC__FN_D
#else
#define MKC__FN_A MKC__FN_F
#endif
#if MKC_ESTEP_DOUBLE
#define MKC__FN_E MKC__FN_D
#else
#define MKC__FN_E MKC__FN_F
#endif

/* mkc_real */
#define MKC_SQRT_R(x) MKC__FN_R(sqrt)(x)
#define MKC_FABS_R(x) MKC__FN_R(fabs)(x)
#define MKC_EXP_R(x) MKC__FN_R(exp)(x)
#define MKC_ATAN2_R(y, x) MKC__FN_R(atan2)(y, x)

/* mkc_acc */
#define MKC_SQRT_A(x) MKC__FN_A(sqrt)(x)
#define MKC_FABS_A(x) MKC__FN_A(fabs)(x)
#define MKC_EXP_A(x) MKC__FN_A(exp)(x)
#define MKC_LOG_A(x) MKC__FN_A(log)(x)

/* mkc_ereal */
#define MKC_SQRT_E(x) MKC__FN_E(sqrt)(x)
#define MKC_FABS_E(x) MKC__FN_E(fabs)(x)
#define MKC_EXP_E(x) MKC__FN_E(exp)(x)
#define MKC_EXPM1_E(x) MKC__FN_E(expm1)(x)
#define MKC_LOG_E(x) MKC__FN_E(log)(x)
#define MKC_LOG1P_E(x) MKC__FN_E(log1p)(x)

#if MKC_ALL_FLOAT
/* the all-float build's own functions (fmath.c) */
float mkc__cbrtf(float x);
float mkc__atan2f_axes(float y, float x);
#define MKC_CBRTF(x) mkc__cbrtf(x)
#else
#define MKC_CBRTF(x) cbrtf(x)
#endif

#endif /* MKC_MATH_H */
