/* mkc_internal.h: declarations shared by the library's translation units (not installed).
 *
 * Numerical convention: every routine mirrors its Python kernel statement by statement, with the
 * same operation order, so that the double build reproduces the Numba kernels to the last bit
 * where only IEEE arithmetic and libm are involved (compile with -ffp-contract=off, never
 * -ffast-math). Every libm call names the precision of its argument (mkc_math.h: MKC_EXP_E is exp
 * or expf as mkc_ereal is double or float); literals are cast with RC/AC/EC so that the float build
 * stays in float (checked with -Wdouble-promotion).
 */
#ifndef MKC_INTERNAL_H
#define MKC_INTERNAL_H

#include "mkc_math.h"

#include "mkc.h"
#include "mkc_tables.h"

/* Arithmetic type of the checkpoint code (sphere fit, geometry, eigen-decompositions, quality,
 * acceptance; once per K samples): double, unless a float build sets -DMKC_CHECKPOINT_DOUBLE=0
 * (mkc_config.h). */
#if defined(MKC_USE_FLOAT) && !MKC_CHECKPOINT_DOUBLE
#define MKC_CREAL_FLOAT 1
typedef float mkc_creal;
#define MKC_SQRT_C(x) sqrtf(x)
#define MKC_FABS_C(x) fabsf(x)
#define MKC_POW_C(x, y) powf(x, y)
#else
#define MKC_CREAL_FLOAT 0
typedef double mkc_creal;
#define MKC_SQRT_C(x) sqrt(x)
#define MKC_FABS_C(x) fabs(x)
#define MKC_POW_C(x, y) pow(x, y)
#endif
#define CR(x) ((mkc_creal)(x))

#define RC(x) ((mkc_real)(x))
#define AC(x) ((mkc_acc)(x))
#define EC(x) ((mkc_ereal)(x))

/* mkc_config_default's settings for n, m as an initializer (stream.c, and mag.c's defaults) */
#define MKC__CONFIG_DEFAULTS(n_, m_) {                                                                   \
    .n = (n_), .m = (m_),                                                                               \
    .window = MKC_W < MKC_DEFAULT_WINDOW ? MKC_W : MKC_DEFAULT_WINDOW, /* min(capacity, the default) */ \
    .estep_every = MKC_K, .fp_rounds = MKC_DEF_FP_ROUNDS, .estep_max_iter = MKC_DEF_ESTEP_MAX_ITER,      \
    .refactor_every = MKC_DEF_REFACTOR_EVERY, .min_samples = MKC_DEF_MIN_SAMPLES,                        \
    .sigma_lo = (mkc_api_real)MKC_DEF_SIGMA_LO, .sigma_hi = (mkc_api_real)MKC_DEF_SIGMA_HI,              \
    .d_lo = (mkc_api_real)MKC_DEF_D_LO, .d_hi = (mkc_api_real)MKC_DEF_D_HI,                              \
    .a_factor = (mkc_api_real)MKC_DEF_A_FACTOR, .a = (mkc_api_real)MKC_DEF_A,                            \
    .estep_gtol = (mkc_api_real)MKC_DEF_ESTEP_GTOL, .fp_tol = (mkc_api_real)MKC_DEF_FP_TOL,              \
    .sigma_start = (mkc_api_real)MKC_DEF_SIGMA_START, .sigma_pull = (mkc_api_real)MKC_DEF_SIGMA_PULL     \
}

/* The public numbers must be the Python ones (generated into mkc_tables.h). */
typedef char mkc__check_status[(MKC_OK == MKC_T_OK && MKC_NOT_CONVERGED == MKC_T_NOT_CONVERGED &&
                                MKC_SINGULAR == MKC_T_SINGULAR && MKC_NONFINITE == MKC_T_NONFINITE &&
                                MKC_BAD_INPUT == MKC_T_BAD_INPUT && MKC_WARMING_UP == MKC_T_WARMING_UP &&
                                MKC_REJECTED == MKC_T_REJECTED) ? 1 : -1];
typedef char mkc__check_counters[(MKC_COUNTERS == MKC_N_COUNTERS && MKC_CNT_FACTORS == MKC_C_FACTORS &&
                                  MKC_CNT_STATUS == MKC_C_STATUS && MKC_CELLS == MKC_N_CELLS) ? 1 : -1];
/* The named fields (mkc_fields.h) hold the Python arrays' entries back to back, no padding: the
 * state's layout is that of the arrays, and introspect.c copies the counters as an int64_t array. */
typedef char mkc__check_named_fields[
    (sizeof(mkc_core_cfg) == MKC_N_ICFG * sizeof(int32_t) + MKC_N_FCFG * sizeof(mkc_real) &&
     sizeof(mkc_counters) == MKC_N_COUNTERS * sizeof(int64_t) &&
     sizeof(mkc_core_fit) == MKC_N_FSTATE * sizeof(mkc_real))
    ? 1 : -1];

/* A value as a reason holds it (mkc_mag_reason.v: float in the all-float build, double otherwise) */
#define MKC_REASON_VALUE(x) ((mkc_api_real)(x))

#define MKC_PI 3.141592653589793238462643383279502884

/* mkc_acc and mkc_real are the same type (double build, all-float build): a copy between them is a
 * plain copy */
#if !defined(MKC_USE_FLOAT) || MKC_ALL_FLOAT
#define MKC_ACC_IS_REAL 1
#else
#define MKC_ACC_IS_REAL 0
#endif

/* Cells' sectors by comparisons instead of atan2 where the arithmetic is float (stats.c
 * mkc__sector_of, for x and y both non-zero). MKC_ATAN2_AXES_R(y, x) is atan2 where that is not so:
 * in the all-float build fmath.c's exact values for a zero x or y, the only ones it is asked. */
#if (MKC_CREAL_FLOAT || MKC_ALL_FLOAT) && MKC_N_SECTORS == 12
#define MKC_SECTOR_BY_COMPARISON 1
int mkc__sector_of(float x, float y);   /* stats.c */
#else
#define MKC_SECTOR_BY_COMPARISON 0
#endif
#if MKC_ALL_FLOAT && MKC_SECTOR_BY_COMPARISON
#define MKC_ATAN2_AXES_R(y, x) mkc__atan2f_axes(y, x)
#else
#define MKC_ATAN2_AXES_R(y, x) MKC_ATAN2_R(y, x)
#endif

/* The reference's 1e-300 floors (below them a quantity is "zero"); FLT_MIN-sized in a float type. */
#if MKC_ACC_DOUBLE
#define MKC_TINY_ACC 1e-300
#else
#define MKC_TINY_ACC 1e-37
#endif

/* A helper kept out of line: at -Os GCC inlines a small static function at each of its call sites
 * even where one call is shorter (checkpoint code, where the call costs nothing that matters). */
#if defined(__GNUC__)
#define MKC_NOINLINE __attribute__((noinline))
#else
#define MKC_NOINLINE
#endif

/* min/max with Numba's semantics for the values that occur: the first argument on ties, NaN wins. */
#define MKC_MIN(a, b) mkc__min_d((double)(a), (double)(b))
static inline double mkc__min_d(double a, double b) { return (a != a) ? a : ((b != b || b < a) ? b : a); }
static inline double mkc__max_d(double a, double b) { return (a != a) ? a : ((b != b || b > a) ? b : a); }
float mkc__min_f(float a, float b);   /* linalg.c: one copy for the library, not one per file */
void mkc__count(int64_t *counter);    /* linalg.c: *counter += 1, the 64-bit increment of the rarer counters */
int mkc__finite_f(float x);           /* linalg.c: isfinite of a float, one copy */
/* isfinite(x) of a float or double x: a float's through mkc__finite_f (-Os expands isfinite at each
 * use), a double's inline (the branch not taken is removed at compile time) */
#define MKC_ISFINITE(x) (sizeof(x) == sizeof(float) ? mkc__finite_f((float)(x)) : isfinite(x))
float mkc__max_f(float a, float b);
#ifdef MKC_USE_FLOAT
#define mkc__min_r mkc__min_f
#define mkc__max_r mkc__max_f
#else
#define mkc__min_r mkc__min_d
#define mkc__max_r mkc__max_d
#endif
#if MKC_ESTEP_DOUBLE
#define mkc__min_e mkc__min_d
#define mkc__max_e mkc__max_d
#else
#define mkc__min_e mkc__min_f
#define mkc__max_e mkc__max_f
#endif
#if MKC_ACC_DOUBLE
#define mkc__max_a mkc__max_d
#define mkc__min_a mkc__min_d
#else
#define mkc__max_a mkc__max_f
#define mkc__min_a mkc__min_f
#endif

#if !MKC_ESTEP_DOUBLE
/* The single-precision E-step (normaliser.c, estep.c). Its objective is flat in sigma: the gradient
 * in sigma is a difference of terms that each cancel to O(1/sigma^2) when written as the double
 * build writes them, which in float leaves no correct digit for sigma >~ 30. Here every such term
 * is a series without cancellation, and the sums are compensated (Kahan), so the float objective
 * follows the double one to a few ulps. */

/* (1 - h, 1 - (1 + q) h, h) with h = e^-q, each to a few ulps relative. Below q = 1/2 (where
 * 1 - h and 1 - (1 + q) h cancel) the Taylor series
 *   1 - h          = sum_{k>=1} (-1)^(k+1) q^k / k!        (through q^8)
 *   1 - (1 + q) h  = sum_{k>=2} (-1)^k (k - 1) q^k / k!    (through q^9)
 * (truncation < 3e-8 relative) and no libm call; above it one expf. */
void mkc__omh_terms_f(float q, float *omh, float *omh_qh, float *h);   /* normaliser.c: one copy */

#define MKC_FLT_EPS 1.1920929e-7f     /* FLT_EPSILON */
#define MKC_GRAD_NOISE_ULPS 16.0f     /* the float E-step gradient's rounding noise, in ulps of its terms */

/* Kahan's compensated sum: *s += x with the rounding error carried in *c. */
static inline void mkc__kahan_add_f(float *s, float *c, float x)
{
    float y = x - *c;
    float t = *s + y;
    *c = (t - *s) - y;
    *s = t;
}
#endif

/* ---- normaliser.c (kernels/normaliser.py) ---- */
mkc_ereal mkc__cut_point(mkc_ereal sigma);
/* log Z(sigma, A); *d_sigma, *d_A: its derivatives. */
mkc_ereal mkc__log_normaliser_grad(mkc_ereal sigma, mkc_ereal A, mkc_ereal *d_sigma, mkc_ereal *d_A);

/* ---- linalg.c (kernels/linalg.py, and the small dense helpers of calib/) ---- */
int mkc__spd_solve(const mkc_acc A[MKC_N][MKC_N], const mkc_acc *b, mkc_acc *x, mkc_acc L[MKC_N][MKC_N],
                   mkc_acc *D, int n, mkc_acc *cond);
/* Cyclic Jacobi eigen-decomposition of a symmetric k x k matrix (k <= 9), stride 9; a is destroyed.
 * Eigenvalues ascending into w; eigenvectors as columns of V (if V != NULL). Returns the sweeps, or
 * -1 if it did not converge within the bound. */
int mkc__jacobi_eigen(mkc_creal a[9][9], int k, mkc_creal *w, mkc_creal V[9][9]);
/* Solve the 3x3 system A x = b by Gaussian elimination with partial pivoting; MKC_SINGULAR if a
 * pivot is 0 (numpy.linalg.solve raises LinAlgError "Singular matrix" then). */
int mkc__solve3(const mkc_creal A[3][3], const mkc_creal *b, mkc_creal *x);

/* ---- estep.c (kernels/estep.py) ---- */
mkc_ereal mkc__estep_objective(mkc_ereal ls, mkc_ereal ld, const mkc_real *e2, int n, mkc_ereal a, mkc_ereal pull,
                               mkc_ereal *g0, mkc_ereal *g1);
int mkc__estep_channel(const mkc_real *e2, int n, mkc_ereal a, mkc_ereal sigma0, mkc_ereal d0, mkc_ereal sig_lo,
                       mkc_ereal sig_hi, mkc_ereal d_lo, mkc_ereal d_hi, int max_iter, mkc_ereal gtol, mkc_ereal pull,
                       mkc_ereal *H, mkc_ereal *sigma, mkc_ereal *d, mkc_ereal *F, int *iters);

/* ---- window.c (kernels/window.py) ---- */
/* Rows of the window: stored (mkc_stream_t) or the ellipsoid features of raw (mkc_mag_t). */
const mkc_real *mkc__row(const mkc_core_t *c, int s, int i, mkc_real *buf);
void mkc__ellipsoid_features(mkc_real mx, mkc_real my, mkc_real mz, const mkc_real *c0, mkc_real s0, mkc_real *xk);
int mkc__core_init(mkc_core_t *c, const mkc_config *cfg, const mkc_real *sigma0, const mkc_real *d0,
                   const mkc_real *theta0, int rows);
int mkc__learn_one(mkc_core_t *c, const mkc_real *xk, const mkc_real *yk, int slot);
int mkc__rebuild(mkc_core_t *c);
/* C := the weights a rebuild round at theta with these sigma, d records for the window's rows (0
 * elsewhere), to the same bits; mkc__weights_recorded: whether C is that for tprev, sigma, d, as the
 * last rebuild round leaves it. */
void mkc__record_weights_at(mkc_core_t *c, const mkc_real *theta, const mkc_real *sigma, const mkc_real *d);
int mkc__weights_recorded(const mkc_core_t *c);
void mkc__estep_window(mkc_core_t *c);
int mkc__restart(mkc_core_t *c);
int mkc__cold_start(mkc_core_t *c, int rounds);
mkc_ereal mkc__window_objective(mkc_core_t *c);
int mkc__restart_at(mkc_core_t *c, const mkc_real *theta0);
int mkc__cold_start_at(mkc_core_t *c, int rounds, const mkc_real *theta0);

/* ---- magwindow.c (kernels/magwindow.py) ---- */
int mkc__direction_cell(mkc_real vx, mkc_real vy, mkc_real vz);
int mkc__choose_slot(const mkc_mag_t *g, int cell, int count, int W);
/* |m_cal| of a raw sample, m_cal = S (raw - b); m (may be NULL): m_cal. The checkpoint code
 * recomputes it from a window row g->raw[k] (quality figures, switching test) instead of keeping it
 * in the state; mkc_mag_apply takes its m_cal. */
mkc_real mkc__calibrated_norm(const mkc_real *raw, const mkc_real *b, const mkc_real S[3][3], mkc_real *m);
/* |raw_k - c|, the distance of window row k from the point c (sphere fit, its spread, the first
 * normalisation). */
mkc_real mkc__raw_distance(const mkc_mag_t *g, int k, const mkc_real *c);
/* out[k] = mkc__calibrated_norm(g->raw[k], b, S, NULL) for k < count (the checkpoint code's passes over
 * the window). */
void mkc__calibrated_norms(const mkc_mag_t *g, int count, const mkc_real *b, const mkc_real S[3][3], mkc_real *out);

void mkc__recount_cells(mkc_mag_t *g, int count);
/* slot has just been written (count: the window's samples before): it gets the newest stamp. */
void mkc__slot_written(mkc_mag_t *g, int slot, int count);

/* ---- stats.c (numpy's reductions, reproduced) ---- */
/* numpy's pairwise summation of x[0..n-1] (np.sum / np.mean of a contiguous float64 array). */
mkc_real mkc__pairwise_sum(const mkc_real *x, int n);
/* np.median: the k-th smallest by selection (x is reordered). */
mkc_real mkc__median(mkc_real *x, int n);
/* calib/quality.py outlier_mask's scale: *med = median(x); returns 1.4826 median|x - med| (work: n values). */
mkc_real mkc__mad_about_median(const mkc_real *x, int n, mkc_real *work, mkc_real *med);
#define MKC_OUTLIER_K 3.5          /* quality.outlier_mask(k=3.5): outliers lie beyond k robust scales */
#define MKC_MAD_SCALE 1.4826       /* robust.MAD_SCALE */
/* Fraction of the 72 direction cells hit by the rows v (n x 3, calib/quality.py sphere_coverage). */
mkc_real mkc__coverage_of_unit_cells(const int *cells_hit, int ncells);
int mkc__unit_direction_cell(mkc_real ux, mkc_real uy, mkc_real uz);

/* ---- sphere.c (calib/ellipsoid.py sphere_fit, robust_sphere_fit) ---- */
int mkc__robust_sphere_fit(mkc_mag_t *g, int count, mkc_real *b, mkc_real *F);
int mkc__sphere_theta(const mkc_creal *c, mkc_creal r, mkc_real *theta);
mkc_real mkc__sphere_coverage_raw(const mkc_mag_t *g, int count, const mkc_real *b);

/* ---- ellipsoid.c (calib/ellipsoid.py geometry_from_theta, raw_geometry, calibration_from_geometry) ---- */
typedef struct mkc__geometry {
    mkc_creal centre[3];
    mkc_creal M[3][3];
} mkc__geometry;
/* Returns MKC_REASON_NONE or the MKC_REASON_* why theta is not an ellipsoid (values into reason). */
int mkc__geometry_from_theta(const mkc_real *theta, mkc__geometry *g, mkc_mag_reason *reason);
void mkc__raw_geometry(mkc__geometry *g, const mkc_real *c0, mkc_real s0);
void mkc__calibration_from_geometry(const mkc__geometry *g, mkc_creal b[3], mkc_creal S[3][3], mkc_creal *F);

/* ---- quality.c (calib/quality.py, calib/fit.py weighted_condition, calib/acceptance.py) ---- */
void mkc__quality_figures(mkc_mag_t *g, int count, const mkc_real *b, const mkc_real S[3][3], mkc_real F,
                          mkc_real condition, mkc_real *q);
mkc_real mkc__weighted_condition(mkc_mag_t *g, int count);
/* disagreement < 0: not checked (the reference's disagreement=None) */
/* The median (*med) and 1.4826 MAD of e_k = |S (raw_k - b)| / div - sub over the window's rows
 * (scratch: g->core.ebuf): the quality figures' residuals (div 1, sub F) and the switching test's
 * relative residuals (div F, sub 1). */
mkc_real mkc__calibrated_mad(mkc_mag_t *g, int count, const mkc_real *b, const mkc_real S[3][3], mkc_real div,
                             mkc_real sub, mkc_real *med);
uint32_t mkc__acceptance_check(const mkc_mag_t *g, const mkc_real *q, mkc_real field, mkc_creal disagreement,
                               mkc_mag_reason *reason);

/* ---- confidence.c (calib/confidence.py supports_switch: 0, 1 or 2 (strongly); calib/quality.py sphere_spread) ---- */
int mkc__supports_switch(mkc_mag_t *g, int count, const mkc_mag_calibration *trial, const mkc_mag_calibration *acc);
/* mag.c: the accepted calibration becomes the switching pool's one member (a restored calibration) */
void mkc__seed_pool(mkc_mag_t *g);
mkc_real mkc__sphere_spread(mkc_mag_t *g, int count, const mkc_real *c, mkc_real r);
/* The coordinate-wise median of raw[0 .. count - 1] into med (sphere.c; scratch: g->core.ebuf) */
void mkc__axis_medians(mkc_mag_t *g, int count, mkc_real *med);
/* 1.4826 MAD of r_k = |raw_k - c| - r over the window's rows, their median into *med (sphere.c;
 * scratch: g->core.ebuf) */
mkc_real mkc__distance_mad(mkc_mag_t *g, int count, const mkc_real *c, mkc_real r, mkc_real *med);

#endif /* MKC_INTERNAL_H */
