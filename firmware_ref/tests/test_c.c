/* test_c: the C port's self-test, without Python (make check; also built with sanitizers and run
 * under valgrind). The cross-check against the Python reference is tests/test_firmware.py.
 *
 *   - a synthetic stream is calibrated and the accepted calibration is close to the truth
 *   - the named settings, counters and fit figures (mkc_fields.h) are the entries mkc_get reports
 *   - bad input (NaN, inf, huge values, a stream that never moves, a rotation about one axis, all-
 *     zero regressors, bad configurations) gives status codes, never a crash or a NaN in the state
 */
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "mkc.h"
#include "mkc_introspect.h"
#include "../tools/synth.h"

#define RC(x) ((mkc_real)(x))
static const double NAN_D = (double)NAN;

static int failures = 0, checks = 0;

#define CHECK(cond, ...)                                                 \
    do {                                                                 \
        checks++;                                                        \
        if (!(cond)) {                                                   \
            failures++;                                                  \
            printf("FAIL %s:%d: ", __FILE__, __LINE__);                  \
            printf(__VA_ARGS__);                                         \
            printf("\n");                                                \
        }                                                                \
    } while (0)

static mkc_mag_t cal;          /* large with host capacities: static, not on the stack */
static mkc_stream_t st;
static double buf[1 << 16];
static double mags[3 * 40000];

/* every float field the estimate depends on is finite (inf only where the reference keeps it: the
 * condition estimate before the first solve) */
static int state_finite(const void *state, int kind)
{
    static const int fields[] = {MKC_F_THETA, MKC_F_SIGMA, MKC_F_D, MKC_F_A, MKC_F_HES, MKC_F_C, MKC_F_LAST_F,
                                 MKC_F_NORMAL_A, MKC_F_NORMAL_B, MKC_F_L, MKC_F_DEQ, MKC_F_XS, MKC_F_TPREV, MKC_F_X};
    size_t f;
    int k, n;
    for (f = 0; f < sizeof(fields) / sizeof(fields[0]); f++) {
        n = mkc_get(state, kind, fields[f], buf, (int)(sizeof(buf) / sizeof(buf[0])));
        for (k = 0; k < n; k++)
            if (!isfinite(buf[k])) {
                printf("  field %d entry %d is %g\n", fields[f], k, buf[k]);
                return 0;
            }
    }
    if (kind == 1) {
        n = mkc_get(state, 1, MKC_F_RAW, buf, (int)(sizeof(buf) / sizeof(buf[0])));
        for (k = 0; k < n; k++)
            if (!isfinite(buf[k]))
                return 0;
        n = mkc_get(state, 1, MKC_F_C0S0, buf, 4);
        for (k = 0; k < n; k++)
            if (!isfinite(buf[k]))
                return 0;
    }
    n = mkc_get(state, kind, MKC_F_COND, buf, 1);
    return n == 1 && !isnan(buf[0]);
}

static void mag_init(int window)
{
    mkc_mag_config cfg;
    mkc_mag_config_default(&cfg);
    cfg.stream.window = window;
    CHECK(mkc_mag_init(&cal, &cfg) == MKC_OK, "mkc_mag_init");
}

static void push_all(const double *m, long T)
{
    long t;
    for (t = 0; t < T; t++)
        mkc_mag_push(&cal, (mkc_real)m[3 * t], (mkc_real)m[3 * t + 1], (mkc_real)m[3 * t + 2]);
}

static void test_synthetic_calibration(void)
{
    const mkc_mag_calibration *acc;
    long T = 12000, k;
    double worst = 0.0;
    mkc_real out[3], in[3];
    mag_init(256);
    synth_mag(mags, T, 1, 0.1, 7);
    CHECK(mkc_mag_apply(&cal, in, out) == MKC_NOT_CALIBRATED, "apply before any acceptance");
    push_all(mags, T);
    acc = mkc_mag_get_calibration(&cal, 1);
    CHECK(acc != NULL, "a calibration is accepted on a 10%% burst sweep");
    if (!acc)
        return;
    for (k = 0; k < 3; k++)
        CHECK(fabs((double)acc->hard_iron[k] - SYNTH_B[k]) < 0.5, "hard iron %d: %g vs %g", (int)k,
              (double)acc->hard_iron[k], SYNTH_B[k]);
    CHECK(fabs((double)acc->field - 50.0 * cbrt(1.10 * 0.92 * 0.99)) < 1.5, "field %g", (double)acc->field);
    /* noise-free points of the true ellipsoid map to a sphere */
    for (k = 0; k < 200; k++) {
        double u[3] = {cos(0.1 * (double)k) * sin(0.07 * (double)k), sin(0.1 * (double)k) * sin(0.07 * (double)k),
                       cos(0.07 * (double)k)}, nrm;
        int i;
        for (i = 0; i < 3; i++)
            in[i] = (mkc_real)(50.0 * (SYNTH_SINV[i][0] * u[0] + SYNTH_SINV[i][1] * u[1] + SYNTH_SINV[i][2] * u[2]) +
                               SYNTH_B[i]);
        CHECK(mkc_mag_apply(&cal, in, out) == MKC_OK, "apply");
        nrm = sqrt((double)(out[0] * out[0] + out[1] * out[1] + out[2] * out[2]));
        if (fabs(nrm / (double)acc->field - 1.0) > worst)
            worst = fabs(nrm / (double)acc->field - 1.0);
    }
    CHECK(worst < 0.01, "calibrated norms within 1%% of F (worst %g)", worst);
    CHECK(state_finite(&cal, 1), "state finite after a good stream");
}

/* After test_synthetic_calibration: each named field is the entry of the Python-ordered array that
 * mkc_get reports for it, and the settings are the configuration's, resolved. */
static void test_named_fields(void)
{
    double cnt[MKC_COUNTERS + 1], cond;
    int64_t samples, bad;
    mkc_mag_config cfg;
    mkc_mag_config_default(&cfg);
    CHECK(mkc_get(&cal, 1, MKC_F_CNT, cnt, MKC_COUNTERS + 1) == MKC_COUNTERS, "mkc_get(MKC_F_CNT) size");
    CHECK(cnt[MKC_CNT_HEAD] == (double)cal.core.counters.head &&
          cnt[MKC_CNT_COUNT] == (double)cal.core.counters.count &&
          cnt[MKC_CNT_SEEN] == (double)cal.core.counters.seen &&
          cnt[MKC_CNT_REJECTED] == (double)cal.core.counters.rejected &&
          cnt[MKC_CNT_ESTEPS] == (double)cal.core.counters.esteps &&
          cnt[MKC_CNT_SINCE] == (double)cal.core.counters.since &&
          cnt[MKC_CNT_STATUS] == (double)cal.core.counters.status &&
          cnt[MKC_CNT_SINGULAR] == (double)cal.core.counters.singular &&
          cnt[MKC_CNT_FP_ITERS] == (double)cal.core.counters.fp_iters &&
          cnt[MKC_CNT_LAST_SLOT] == (double)cal.core.counters.last_slot &&
          cnt[MKC_CNT_RESTARTS] == (double)cal.core.counters.restarts &&
          cnt[MKC_CNT_FACTOR_AGE] == (double)cal.core.counters.factor_age &&
          cnt[MKC_CNT_FACTORS] == (double)cal.core.counters.factors, "named counters are mkc_get's entries");
    CHECK(cal.core.counters.count == 256 && cal.core.counters.esteps > 100 && cal.core.counters.fp_iters > 0,
          "counters after a 12000-sample stream: count %lld, esteps %lld", (long long)cal.core.counters.count,
          (long long)cal.core.counters.esteps);
    mkc_mag_counts(&cal, &samples, &bad);
    CHECK(bad == cal.core.counters.rejected && samples == cal.core.counters.seen + bad + cal.pending,
          "mkc_mag_counts from the named counters");
    CHECK(mkc_get(&cal, 1, MKC_F_COND, &cond, 1) == 1 && cond == (double)cal.core.fit.cond && cond >= 1.0,
          "fit.cond is mkc_get(MKC_F_COND): %g", cond);
    CHECK(cal.core.cfg.n == 9 && cal.core.cfg.m == 1 && cal.core.cfg.window == 256 &&
          cal.core.cfg.estep_every == cfg.stream.estep_every && cal.core.cfg.fp_rounds == cfg.stream.fp_rounds &&
          cal.core.cfg.estep_max_iter == cfg.stream.estep_max_iter && cal.core.cfg.min_samples > 0 &&
          cal.core.cfg.refactor_every > 0, "integer settings");
    CHECK(cal.core.cfg.sigma_lo == (mkc_real)cfg.stream.sigma_lo &&
          cal.core.cfg.sigma_hi == (mkc_real)cfg.stream.sigma_hi &&
          cal.core.cfg.d_lo == (mkc_real)cfg.stream.d_lo && cal.core.cfg.d_hi == (mkc_real)cfg.stream.d_hi &&
          cal.core.cfg.a_factor == (mkc_real)cfg.stream.a_factor && cal.core.cfg.a == (mkc_real)cfg.stream.a &&
          cal.core.cfg.estep_gtol == (mkc_real)cfg.stream.estep_gtol &&
          cal.core.cfg.fp_tol == (mkc_real)cfg.stream.fp_tol &&
          cal.core.cfg.sigma_start == (mkc_real)cfg.stream.sigma_start &&
          cal.core.cfg.sigma_pull == (mkc_real)cfg.stream.sigma_pull, "real settings");
}

static void test_bad_samples(void)
{
    long T = 6000, t, rejected = 0;
    int64_t samples, bad;
    synth_mag(mags, T, 1, 0.0, 11);
    mag_init(256);
    for (t = 0; t < T; t++) {
        double x = mags[3 * t], y = mags[3 * t + 1], z = mags[3 * t + 2];
        int s, expect_reject = 0;
        if (t % 50 == 3) {
            y = (double)NAN;
            expect_reject = 1;
        } else if (t % 97 == 5) {
            x = -HUGE_VAL;
            expect_reject = 1;
        } else if (t % 131 == 7) {
            z = 1e300;                /* beyond MKC_MAX_ABS_INPUT in either precision */
            expect_reject = 1;
        } else if (t % 173 == 9) {
            x = 1e6;                  /* huge but accepted as data (a burst the kernel down-weights) */
        }
        s = mkc_mag_push(&cal, (mkc_real)x, (mkc_real)y, (mkc_real)z);
        if (expect_reject) {
            rejected++;
            CHECK(s == MKC_REJECTED, "sample %ld: status %d, expected MKC_REJECTED", t, s);
        } else {
            CHECK(s >= MKC_OK && s <= MKC_REJECTED, "sample %ld: status %d", t, s);
        }
    }
    mkc_mag_counts(&cal, &samples, &bad);
    CHECK(bad == rejected && samples == T, "counts: %lld bad of %lld, expected %ld of %ld", (long long)bad,
          (long long)samples, rejected, T);
    CHECK(state_finite(&cal, 1), "state finite after NaN/inf/huge samples");
    CHECK(mkc_mag_get_calibration(&cal, 1) != NULL, "still calibrates through the bad samples");
}

static void test_degenerate_streams(void)
{
    long T = 3000, t;
    int s;
    /* the sensor never moves */
    mag_init(128);
    for (t = 0; t < T; t++) {
        s = mkc_mag_push(&cal, RC(31.0), RC(-4.0), RC(17.5));
        CHECK(s >= MKC_OK && s <= MKC_REJECTED, "constant stream: status %d", s);
    }
    CHECK(mkc_mag_get_calibration(&cal, 1) == NULL, "a constant stream is never accepted");
    CHECK(state_finite(&cal, 1), "state finite on a constant stream");
    /* rotation about one axis only */
    mag_init(256);
    for (t = 0; t < 5000; t++) {
        double a = 0.025 * (double)t;
        mkc_mag_push(&cal, (mkc_real)(30.0 * cos(a) + 5.0), (mkc_real)(30.0 * sin(a) - 3.0), RC(20.0));
    }
    CHECK(mkc_mag_get_calibration(&cal, 1) == NULL, "a planar rotation is never accepted");
    CHECK(state_finite(&cal, 1), "state finite on a planar rotation");
    /* all zeros, then tiny values */
    mag_init(64);
    for (t = 0; t < 2000; t++)
        mkc_mag_push(&cal, t < 1000 ? RC(0.0) : (mkc_real)(1e-30 * (double)(t % 7)), RC(0.0), RC(0.0));
    CHECK(state_finite(&cal, 1), "state finite on zeros and denormal-sized values");
    /* only NaN: nothing is ever gathered */
    mag_init(64);
    for (t = 0; t < 500; t++)
        CHECK(mkc_mag_push(&cal, RC(NAN_D), RC(NAN_D), RC(NAN_D)) == MKC_REJECTED, "NaN stream");
    CHECK(state_finite(&cal, 1), "state finite on a NaN stream");
}

static void test_generic_stream(void)
{
    mkc_config cfg;
    mkc_real x[8], y[2];
    long t;
    int s, i, singular = 0;
    synth_rng r;
    r.s = 99;
    mkc_config_default(&cfg, 4, 2);
    cfg.window = 64;
    cfg.estep_every = 8;
    CHECK(mkc_stream_init(&st, &cfg, NULL, NULL, NULL) == MKC_OK, "init 4x2");
    /* all-zero regressors: nothing can be solved */
    for (t = 0; t < 200; t++) {
        for (i = 0; i < 8; i++)
            x[i] = RC(0.0);
        y[0] = RC(1.0);
        y[1] = RC(-1.0);
        s = mkc_stream_learn_one(&st, x, y, -1);
        singular += s == MKC_SINGULAR;
        CHECK(s == MKC_WARMING_UP || s == MKC_SINGULAR, "zero rows: status %d", s);
    }
    CHECK(singular > 0, "zero rows report MKC_SINGULAR");
    CHECK(state_finite(&st, 0), "state finite after singular windows");
    /* then a real linear stream with outliers, NaN, inf and huge samples */
    for (t = 0; t < 4000; t++) {
        for (i = 0; i < 8; i++)
            x[i] = (mkc_real)synth_normal(&r);
        y[0] = x[0] - RC(2.0) * x[1] + RC(0.5) * x[2] + x[3] + (mkc_real)(0.1 * synth_normal(&r));
        y[1] = x[4] - RC(2.0) * x[5] + RC(0.5) * x[6] + x[7] + (mkc_real)(0.1 * synth_normal(&r));
        if (t % 10 == 0)
            y[1] += RC(30.0);
        if (t % 37 == 1)
            x[2] = RC(NAN_D);
        if (t % 41 == 2)
            y[0] = RC(HUGE_VAL);
        if (t % 43 == 3)
            x[5] = (mkc_real)1e300;
        s = mkc_stream_learn_one(&st, x, y, -1);
        CHECK(s >= MKC_OK && s <= MKC_REJECTED, "linear stream: status %d", s);
        if (t % 37 == 1 || t % 41 == 2 || t % 43 == 3)
            CHECK(s == MKC_REJECTED, "bad sample %ld: status %d", t, s);
    }
    CHECK(state_finite(&st, 0), "state finite on the linear stream");
    mkc_get(&st, 0, MKC_F_THETA, buf, 4);
    CHECK(fabs(buf[0] - 1.0) < 0.05 && fabs(buf[1] + 2.0) < 0.05 && fabs(buf[2] - 0.5) < 0.05 && fabs(buf[3] - 1.0) < 0.05,
          "theta = (%g, %g, %g, %g), truth (1, -2, 0.5, 1)", buf[0], buf[1], buf[2], buf[3]);
}

static void test_configuration(void)
{
    mkc_config cfg;
    mkc_mag_config mc;
    mkc_real bad_sigma[1] = {RC(-1.0)};
    mkc_config_default(&cfg, 9, 1);
    cfg.window = MKC_W + 1;
    CHECK(mkc_stream_init(&st, &cfg, NULL, NULL, NULL) == MKC_BAD_INPUT, "window beyond MKC_W");
    mkc_config_default(&cfg, 9, 1);
    cfg.window = 4;
    CHECK(mkc_stream_init(&st, &cfg, NULL, NULL, NULL) == MKC_BAD_INPUT, "window < n");
    mkc_config_default(&cfg, 9, 1);
    cfg.sigma_lo = 2000.0;
    CHECK(mkc_stream_init(&st, &cfg, NULL, NULL, NULL) == MKC_BAD_INPUT, "sigma_lo > sigma_hi");
    mkc_config_default(&cfg, 9, 1);
    cfg.d_hi = (mkc_api_real)NAN;
    CHECK(mkc_stream_init(&st, &cfg, NULL, NULL, NULL) == MKC_BAD_INPUT, "NaN bound");
    mkc_config_default(&cfg, 9, 1);
    CHECK(mkc_stream_init(&st, &cfg, bad_sigma, NULL, NULL) == MKC_BAD_INPUT, "negative sigma0");
    {
        mkc_real x[9] = {RC(1.0)}, y[1] = {RC(1.0)};
        CHECK(mkc_stream_learn_one(&st, x, y, -1) == MKC_BAD_INPUT, "a state whose init failed refuses samples");
    }
    mkc_mag_config_default(&mc);
    mc.init_samples = mc.stream.window + 1;
    CHECK(mkc_mag_init(&cal, &mc) == MKC_BAD_INPUT, "init_samples > window");
    mkc_mag_config_default(&mc);
    mc.policy = 7;
    CHECK(mkc_mag_init(&cal, &mc) == MKC_BAD_INPUT, "unknown policy");
}

/* The window's write order survives the 16-bit stamps running out: past 65,535 samples (the stamps
 * renumbered at least once) a slot's stamp is smaller than another's exactly when it was written
 * earlier (the reference's ages compare so). One E-step only (K beyond the stream), W = 32. */
static void test_slot_order_past_stamp_range(void)
{
    mkc_mag_config cfg;
    int64_t written_at[MKC_W];
    long t, T = 70000;
    int s, u, W = 32, wrong = 0, tracked = 0;
    mkc_mag_config_default(&cfg);
    cfg.stream.window = W;
    cfg.stream.estep_every = 1000000;
    CHECK(mkc_mag_init(&cal, &cfg) == MKC_OK, "mkc_mag_init");
    for (s = 0; s < MKC_W; s++)
        written_at[s] = -1;
    for (t = 0; t < T; t++) {
        double a = 0.37 * (double)t, b = 0.011 * (double)t;
        int64_t seen = cal.core.counters.seen;
        mkc_mag_push(&cal, (mkc_real)(50.0 * cos(a) * sin(b) + 5.0), (mkc_real)(50.0 * sin(a) * sin(b) - 3.0),
                     (mkc_real)(50.0 * cos(b) + 1.0));
        if (cal.core.counters.seen > seen)
            written_at[cal.core.counters.last_slot] = (int64_t)t;
    }
    CHECK(cal.core.counters.seen > 65535 && cal.core.counters.count == W, "stream past the stamps' range (%ld seen)",
          (long)cal.core.counters.seen);
    for (s = 0; s < W; s++) {
        tracked += written_at[s] >= 0;      /* (the first normalisation's samples enter together) */
        for (u = 0; u < W; u++)
            if (s != u && written_at[s] >= 0 && written_at[u] >= 0 &&
                (written_at[s] < written_at[u]) != (cal.slot_stamp[s] < cal.slot_stamp[u]))
                wrong++;
    }
    CHECK(tracked >= W / 2, "slots written after the first normalisation: %d", tracked);
    CHECK(wrong == 0, "slot stamps in write order (%d pairs out of order)", wrong);
}

int main(void)
{
    test_synthetic_calibration();
    test_named_fields();
    test_bad_samples();
    test_degenerate_streams();
    test_generic_stream();
    test_configuration();
    test_slot_order_past_stamp_range();
    printf("test_c (%s): %d checks, %d failures\n", sizeof(mkc_real) == 8 ? "double" : "float", checks, failures);
    return failures ? 1 : 0;
}
