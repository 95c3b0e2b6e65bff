/* mkc_config.h: compile-time sizes and the float/double switch of the mkc C99 port.
 *
 * Every array of the state is sized here, so the state is one plain struct (no malloc). The sizes
 * are capacities: a state may be configured at run time with n <= MKC_N, m <= MKC_M,
 * W <= MKC_W (the Python StreamConfig's n, m, window); firmware compiles the exact sizes it uses
 * (the defaults: the 9-parameter ellipsoid, one channel, W = 256), host tools compile larger ones.
 *
 * Override on the command line, e.g. `-DMKC_W=512 -DMKC_USE_FLOAT`.
 */
#ifndef MKC_CONFIG_H
#define MKC_CONFIG_H

#ifndef MKC_N
#define MKC_N 9        /* parameters (9: the ellipsoid of eq. (36)-(37)) */
#endif
#ifndef MKC_M
#define MKC_M 1        /* residual channels */
#endif
#ifndef MKC_W
#define MKC_W 256      /* window: samples kept */
#endif
#ifndef MKC_K
#define MKC_K 32       /* default E-step period (a run-time setting; not a size) */
#endif

#if MKC_N < 1 || MKC_M < 1 || MKC_W < 2
#error "mkc_config.h: MKC_N, MKC_M must be >= 1 and MKC_W >= 2"
#endif
#if MKC_W > 65535
#error "mkc_config.h: MKC_W must fit the 16-bit cell counters (<= 65535)"
#endif

/* Storage and arithmetic precision. Default double: bit-for-bit the Python reference's kernels.
 * -DMKC_USE_FLOAT stores every window and estimate value in float (the memory of a small MCU) and
 * keeps three parts in double arithmetic by default (see README "The float build"):
 *   MKC_ACC_DOUBLE        the window's normal equations A, b, their Cholesky factor and solves
 *   MKC_ESTEP_DOUBLE      the E-step objective, the normaliser quadrature and the BFGS iterate
 *   MKC_CHECKPOINT_DOUBLE the checkpoint code: sphere fit, geometry, eigen-decompositions, quality
 * Measured: with all three, one checkpoint of the float build from the reference's state differs
 * from it by <= 1e-5 (theta, calibration). -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0 gives the
 * all-float build for an FPU without double, and with it the checkpoint code in float too
 * (MKC_CHECKPOINT_DOUBLE defaults to 0 there): its E-step evaluates the objective and gradient
 * without cancellation (series, compensated sums) and learns curvature only from gradient changes
 * above float rounding (estep.c); its sphere fit forms residuals and sums in float-float
 * (sphere.c, mkc_ff.h) so that it rounds to the double build's floats, and its rebuild sums the
 * normal equations with compensation (window.c). Free-running, its accepted calibrations stay within
 * 1e-4 of the reference on every golden vector, with the same decisions (host: <= 7.2e-5,
 * tools/measure_float_precision.py; emulated Cortex-M4F: <= 3.4e-5, tests/test_cortex_m.py). */
#ifdef MKC_USE_FLOAT
typedef float mkc_real;
#ifndef MKC_ACC_DOUBLE
#define MKC_ACC_DOUBLE 1
#endif
#ifndef MKC_ESTEP_DOUBLE
#define MKC_ESTEP_DOUBLE 1
#endif
#else
typedef double mkc_real;
#undef MKC_ACC_DOUBLE
#undef MKC_ESTEP_DOUBLE
#define MKC_ACC_DOUBLE 1
#define MKC_ESTEP_DOUBLE 1
#endif

/* accumulator type of the normal equations */
#if MKC_ACC_DOUBLE
typedef double mkc_acc;
#else
typedef float mkc_acc;
#endif

/* the checkpoint code's arithmetic (mkc_internal.h mkc_creal): float in the all-float build (no
 * double arithmetic), double in the others; -DMKC_CHECKPOINT_DOUBLE=0 or 1 chooses in a float build */
#ifndef MKC_CHECKPOINT_DOUBLE
#if defined(MKC_USE_FLOAT) && !MKC_ACC_DOUBLE && !MKC_ESTEP_DOUBLE
#define MKC_CHECKPOINT_DOUBLE 0
#else
#define MKC_CHECKPOINT_DOUBLE 1
#endif
#endif

/* MKC_ALL_FLOAT: no double arithmetic anywhere (the build for an FPU without double) */
#if defined(MKC_USE_FLOAT) && !MKC_ACC_DOUBLE && !MKC_ESTEP_DOUBLE
#define MKC_ALL_FLOAT 1
#else
#define MKC_ALL_FLOAT 0
#endif

/* the real type of the public API's run-time settings (mkc_config) and reason values
 * (mkc_mag_reason.v): float in the all-float build, where a double would be converted by libgcc's
 * software double on an FPU without double; double in the others */
#if MKC_ALL_FLOAT
typedef float mkc_api_real;
#else
typedef double mkc_api_real;
#endif

/* arithmetic type of the E-step (objective, normaliser, BFGS) */
#if MKC_ESTEP_DOUBLE
typedef double mkc_ereal;
#else
typedef float mkc_ereal;
#endif

#endif /* MKC_CONFIG_H */
