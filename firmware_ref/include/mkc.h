/* mkc.h: the public header of the mkc C99 reference port (firmware_ref/); mkc_introspect.h adds the
 * field-by-field access that the self-test, the host tools and the Python bridge use.
 *
 * A plain C99 port of mkc_stream's streaming MKC-EM regression and its magnetometer calibrator:
 *   mkc_stream_*  the generic streaming estimator (n parameters, m channels, window W, E-step every K):
 *                 mkc_stream/kernels/{window,estep,normaliser,linalg,correntropy}.py
 *   mkc_mag_*     the ellipsoid calibrator on a direction-organised window, its trial/accepted
 *                 calibrations and acceptance predicate: kernels/magwindow.py, calib/streaming.py,
 *                 calib/ellipsoid.py, calib/quality.py, calib/acceptance.py
 *
 * Rules: no malloc, no globals, no I/O; every symbol is prefixed mkc_; the state pointer comes first
 * in every call; failures are status codes (never NaN in the state). Sizes and precision come from
 * mkc_config.h. All states are plain structs: zero-initialise, then call the *_init function.
 */
#ifndef MKC_H
#define MKC_H

#include <stddef.h>
#include <stdint.h>

#include "mkc_config.h"
#include "mkc_fields.h"

#ifdef __cplusplus
extern "C" {
#endif

/* ---- status codes (the numbers of mkc_stream/kernels/__init__.py and kernels/window.py) ---- */
enum {
    MKC_OK = 0,             /* step done */
    MKC_NOT_CONVERGED = 1,  /* iteration cap reached; the result is the last iterate */
    MKC_SINGULAR = 2,       /* normal equations not positive definite; the previous estimate was kept */
    MKC_NONFINITE = 3,      /* a NaN/inf appeared; the previous estimate was kept */
    MKC_BAD_INPUT = 4,      /* arguments outside the domain (configuration, sizes, pointers) */
    MKC_WARMING_UP = 5,     /* fewer than min_samples in the window: nothing solved yet */
    MKC_REJECTED = 6,       /* the sample had NaN/inf (or |value| > MKC_MAX_ABS_INPUT) and was not used */
    MKC_NOT_CALIBRATED = 7  /* mkc_mag_apply: no calibration accepted yet */
};

/* Inputs larger than this (in absolute value) are rejected like NaN (the Python reference accepts
 * any finite value; here products of features must stay finite in the normal equations):
 * MKC_MAX_ABS_INPUT bounds every sample value (mkc_stream_* and mkc_mag_*), MKC_MAX_ABS_NORMALISED
 * the magnetometer's normalised coordinates (m - c0) / s0. */
#ifdef MKC_USE_FLOAT
#define MKC_MAX_ABS_INPUT 1e15f
#define MKC_MAX_ABS_NORMALISED 1e8f
#else
#define MKC_MAX_ABS_INPUT 1e100
#define MKC_MAX_ABS_NORMALISED 1e60
#endif

#define MKC_CELLS 72         /* direction cells: 6 bands uniform in z x 12 sectors of 30 degrees */
#define MKC_QUALITY 7        /* quality figures, order below */

/* quality figure indices (calib/quality.py quality_figures, same order as its dict) */
enum {
    MKC_Q_RESIDUAL_RMS = 0, MKC_Q_RESIDUAL_RMS_ALL, MKC_Q_NORM_SPREAD, MKC_Q_NORM_SPREAD_INLIERS,
    MKC_Q_COVERAGE, MKC_Q_OUTLIER_FRACTION, MKC_Q_CONDITION
};

/* ---- configuration of the generic stream (mkc_stream/state.py StreamConfig) ---- */
typedef struct mkc_config {
    int n, m, window, estep_every;
    int fp_rounds;          /* fixed-point rounds per rebuild */
    int estep_max_iter;     /* BFGS iterations per channel per E-step */
    int refactor_every;     /* tracking steps between Cholesky refreshes (0: min(K, max(1, W/8))) */
    int min_samples;        /* samples before the first solve (0: ceil(max(2n, n+8) / m)) */
    /* mkc_api_real: float in the all-float build, double otherwise (mkc_config.h) */
    mkc_api_real sigma_lo, sigma_hi, d_lo, d_hi, a_factor, a, estep_gtol, fp_tol, sigma_start;
    mkc_api_real sigma_pull;  /* weak prior on sigma, nats per e-fold (0: the paper's ML) */
} mkc_config;

/* ---- the state (mkc_stream/state.py STATE_FIELDS; X, Y in the outer struct, scratch ebuf last; the
 * Python scratch R, the window's residuals, is not kept: they are formed where they are used) ----
 * The Python state's small arrays are named structs here (mkc_fields.h, generated from the same
 * index table): icfg + fcfg = cfg, cnt = counters, fst = fit; e.g. cal.core.cfg.window,
 * cal.core.counters.esteps, cal.core.fit.cond. Read any field; write only through the API. */
typedef struct mkc_core {
    mkc_core_cfg cfg;                /* the settings it runs with (Python icfg, fcfg) */
    int32_t rows;                    /* where rows come from: 0 X/Y of mkc_stream_t, 1 raw of mkc_mag_t */
    int32_t defer_weights;           /* 0: rebuilds record C; 1, 2: they do not (2: one has run) while the
                                        magnetometer's cold-start check keeps the warm estimate in C's bytes */
    mkc_real C[MKC_W][MKC_M];        /* the c = w/d^2 each row added */
    mkc_acc A[MKC_N][MKC_N];         /* weighted normal matrix (eq. 15), lower triangle */
    mkc_acc b[MKC_N];                /* weighted normal vector (eq. 15) */
    mkc_real theta[MKC_N];           /* estimate */
    mkc_real sigma[MKC_M];           /* kernel bandwidth per channel */
    mkc_real d[MKC_M];               /* nominal deviation per channel (<= 0: unset) */
    mkc_real a[MKC_M];               /* truncation bound per channel at the last E-step */
    mkc_ereal Hes[MKC_M][3];         /* E-step inverse-Hessian warm start per channel */
    mkc_acc L[MKC_N][MKC_N];         /* Cholesky factor kept for the per-sample tracking */
    mkc_acc D[MKC_N];                /* its equilibration */
    mkc_acc xs[MKC_N];               /* scratch: solution */
    mkc_real tprev[MKC_N];           /* scratch: previous theta */
    mkc_counters counters;           /* what it has done: samples, E-steps, restarts, last status (cnt) */
    mkc_core_fit fit;                /* condition of A, last E-step objective (fst) */
    /* scratch last (A .. fit and C are what a saved estimate needs; see MKC_CORE_SAVED_BYTES) */
    mkc_real ebuf[MKC_W];            /* scratch: one channel's squared residuals (E-step), checkpoint scratch */
} mkc_core_t;

/* Bytes of the estimate's state after its weights (A through fit): what the magnetometer's cold-start
 * check keeps in the bytes of C (the weights themselves are recomputed from tprev, sigma and d); the
 * part beyond C's size, if any (a window of fewer than ~250 slots), in mkc_mag_t.saved_tail. */
#define MKC_CORE_SAVED_BYTES (offsetof(mkc_core_t, ebuf) - offsetof(mkc_core_t, A))
#define MKC_CORE_C_BYTES (sizeof(mkc_real) * MKC_W * MKC_M)
#define MKC_SAVED_TAIL_BYTES (MKC_CORE_SAVED_BYTES > MKC_CORE_C_BYTES ? MKC_CORE_SAVED_BYTES - MKC_CORE_C_BYTES : 1)

typedef struct mkc_stream {
    mkc_core_t core;                 /* first member: the kernels see a mkc_core_t */
    mkc_real X[MKC_W][MKC_M][MKC_N]; /* ring buffer: regressor rows */
    mkc_real Y[MKC_W][MKC_M];        /* ring buffer: targets */
} mkc_stream_t;

/* Defaults of StreamConfig for n parameters, m channels; window MKC_W (capped at >= n), K MKC_K. */
void mkc_config_default(mkc_config *cfg, int n, int m);

/* Initialise (sigma0, d0: per channel or NULL for 20 / unset; theta0: NULL for 0). */
int mkc_stream_init(mkc_stream_t *st, const mkc_config *cfg, const mkc_real *sigma0, const mkc_real *d0,
                    const mkc_real *theta0);
/* Feed one sample: x (m x n, row-major), y (m). slot < 0: the ring buffer's head. Returns a status. */
int mkc_stream_learn_one(mkc_stream_t *st, const mkc_real *x, const mkc_real *y, int slot);
/* learn_one over T samples (X: T x m x n, Y: T x m); status_out (T) may be NULL. Returns the last status. */
int mkc_stream_learn_many(mkc_stream_t *st, const mkc_real *X, const mkc_real *Y, long T, int8_t *status_out);
/* y_hat = x theta for one sample (x: m x n); out (m). */
void mkc_stream_predict(const mkc_stream_t *st, const mkc_real *x, mkc_real *out);

/* ---- the magnetometer calibrator (calib/streaming.py MagCalibrator) ---- */
enum { MKC_POLICY_FIFO = 0, MKC_POLICY_DIRECTION = 1 };
/* how a passing trial reaches the accepted calibration (calib/streaming.py SWITCHING) */
enum { MKC_SWITCH_PAIRED = 0, MKC_SWITCH_POOLED = 1 };

/* failed acceptance criteria (calib/acceptance.py check), bits of mkc_mag_reason.fails */
enum {
    MKC_FAIL_COVERAGE = 1, MKC_FAIL_CONDITION = 2, MKC_FAIL_OUTLIERS = 4, MKC_FAIL_RESIDUAL = 8,
    MKC_FAIL_FIELD_RANGE = 16, MKC_FAIL_FIELD_NONPOSITIVE = 32, MKC_FAIL_DISAGREEMENT = 64
};

/* why the calibrator has no (new) accepted calibration: the code of MagCalibrator.status_reason() */
enum {
    MKC_REASON_NONE = 0,          /* accepted ("") */
    MKC_REASON_INITIAL,           /* "warming up: not enough samples yet" */
    MKC_REASON_PENDING,           /* "warming up: {v0}/{v1} samples" (gathering the first normalisation) */
    MKC_REASON_WINDOW,            /* "warming up: {v0}/{v1} samples in the window" */
    MKC_REASON_COVERAGE_WAIT,     /* "waiting for orientation coverage ({v0:.0%} ...)" */
    MKC_REASON_NOT_FINITE,        /* trial is not an ellipsoid: parameters not finite */
    MKC_REASON_INDEFINITE,        /* trial is not an ellipsoid: A indefinite (v0..v2 its eigenvalues) */
    MKC_REASON_EMPTY,             /* trial is not an ellipsoid: empty/imaginary (v0 = 1 + r0'A r0) */
    MKC_REASON_SINGULAR,          /* trial is not an ellipsoid: singular matrix */
    MKC_REASON_REJECTED,          /* the predicate failed: fails bits; v0 coverage, v1 condition,
                                     v2 outlier fraction, v3 residual/field, v4 field,
                                     v5 cold-start disagreement */
    MKC_REASON_MOTION_WAIT,       /* "waiting for motion: the window is a cloud ..." (v0 its spread) */
    MKC_REASON_DEGENERATE         /* no E-step yet and the normal equations singular: no ellipsoid */
};

typedef struct mkc_mag_reason {
    int32_t code;
    uint32_t fails;
    mkc_api_real v[6];               /* float in the all-float build, double otherwise */
} mkc_mag_reason;

typedef struct mkc_mag_rules {       /* calib/acceptance.py AcceptanceRules */
    mkc_real min_coverage, max_condition, max_outlier_fraction, max_residual_rel, field_lo_ut, field_hi_ut;
    mkc_real max_disagreement_rel;   /* cold-start confirmation of a new calibration (fraction of F) */
} mkc_mag_rules;

typedef struct mkc_mag_config {
    mkc_config stream;               /* n = 9, m = 1 (forced) */
    int policy;                      /* MKC_POLICY_DIRECTION (default) or MKC_POLICY_FIFO */
    int unit_ut;                     /* 1: samples are in uT, check the physical field range */
    int init_samples;                /* samples for the first normalisation (0: min(W, 64)); <= W */
    mkc_mag_rules rules;
    int switching;                   /* MKC_SWITCH_POOLED (default) or MKC_SWITCH_PAIRED */
} mkc_mag_config;

typedef struct mkc_mag_calibration { /* calib/streaming.py Calibration */
    mkc_real hard_iron[3];
    mkc_real soft_iron[3][3];        /* m_cal = S (m_raw - b), S symmetric positive definite, det S = 1 */
    mkc_real field;
    mkc_real sigma, d;
    mkc_real quality[MKC_QUALITY];
    int32_t valid, accepted;
    mkc_mag_reason reason;           /* why it was not accepted (code MKC_REASON_NONE when it was) */
    int64_t samples_seen, esteps;
} mkc_mag_calibration;

typedef struct mkc_mag_event {       /* calib/streaming.py CheckpointEvent */
    int64_t samples_seen, esteps;
    int32_t accepted, has_calibration;
    mkc_mag_reason reason;
    mkc_real hard_iron[3], field, coverage, outlier_fraction;
} mkc_mag_event;

struct mkc_mag;
/* Called at the end of every checkpoint (E-step) with the calibrator (its last_event filled). */
typedef void (*mkc_mag_listener)(void *user, const struct mkc_mag *cal);

#if MKC_W > 32768
#error "mkc.h: MKC_W > 32768 (mkc_mag_t.slot_stamp is 16 bits)"
#endif

typedef struct mkc_mag {
    mkc_core_t core;                 /* first member: the kernels see a mkc_core_t (rows = 1) */
    mkc_real raw[MKC_W][3];          /* each slot's raw sample: features are recomputed, not stored */
    uint16_t cell_count[MKC_CELLS];  /* samples of the window per direction cell */
    uint8_t slot_cell[MKC_W];        /* direction cell of each slot */
    uint16_t slot_stamp[MKC_W];      /* the order the slots were written in (smaller: older), as the
                                        reference's ages; renumbered 0 .. count-1 when next_stamp is full */
    uint16_t next_stamp;             /* the next slot written gets this stamp */
    mkc_real c0[3], s0;              /* feature normalisation (m - c0) / s0; s0 <= 0: not set yet */
    mkc_real in_raw[3];              /* the sample being fed (written to raw[slot] by learn_one) */
    int32_t policy, unit_ut, init_samples, pending, provisional, failed, misfit, has_confirmed;
    mkc_real confirmed_b[3], confirmed_F;  /* the calibration the last cold start confirmed */
    mkc_mag_rules rules;
    mkc_mag_calibration trial, accepted;
    int64_t first_accepted_at;       /* samples seen at the first acceptance, -1: never */
    int32_t switching;               /* MKC_SWITCH_POOLED or MKC_SWITCH_PAIRED */
    int32_t pool_n, pool_streak;     /* trials in the pool, disagreeing trials in a row */
    mkc_acc pool_mean[13];           /* the pool's running mean of (b, S row-major, F) */
    int64_t checkpoints;             /* checkpoints done */
    mkc_mag_reason last_reason;
    mkc_mag_event last_event;
    mkc_mag_listener listener;
    void *listener_user;
    unsigned char saved_tail[MKC_SAVED_TAIL_BYTES]; /* the saved estimate's bytes beyond C's size */
} mkc_mag_t;

/* Defaults of MagCalibrator(window=MKC_W, estep_every=MKC_K, unit="uT", policy="direction"). */
void mkc_mag_config_default(mkc_mag_config *cfg);
int mkc_mag_init(mkc_mag_t *cal, const mkc_mag_config *cfg);
void mkc_mag_set_listener(mkc_mag_t *cal, mkc_mag_listener fn, void *user);
/* Feed one raw sample; returns the kernel status of the step (MKC_REJECTED for NaN/inf/huge). */
int mkc_mag_push(mkc_mag_t *cal, mkc_real mx, mkc_real my, mkc_real mz);
/* Feed T samples (T x 3); status_out (T) may be NULL. Returns the last status. */
int mkc_mag_push_many(mkc_mag_t *cal, const mkc_real *mags, long T, int8_t *status_out);
/* m_cal = S (raw - b) with the ACCEPTED calibration; MKC_NOT_CALIBRATED before the first one. */
int mkc_mag_apply(const mkc_mag_t *cal, const mkc_real raw[3], mkc_real out[3]);
/* MagCalibrator.status_reason(): why not (yet) accepted; code MKC_REASON_NONE when accepted. */
void mkc_mag_status_reason(const mkc_mag_t *cal, mkc_mag_reason *out);
/* MagCalibrator.counts(): samples (seen + rejected + pending), bad_frames (rejected). */
void mkc_mag_counts(const mkc_mag_t *cal, int64_t *samples, int64_t *bad_frames);

/* The trial (accepted = 0) or accepted (1) calibration, NULL when there is none yet. */
const mkc_mag_calibration *mkc_mag_get_calibration(const mkc_mag_t *cal, int accepted);
const mkc_mag_event *mkc_mag_get_event(const mkc_mag_t *cal);

#ifdef __cplusplus
}
#endif

#endif /* MKC_H */
