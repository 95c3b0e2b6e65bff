/* mkc_replay: replay a recording (docs/spec/recording.md) through the C port's magnetometer calibrator
 * and print the final calibration as the `calibrate` JSON of docs/spec/machine-output.md (the object
 * `mkc-stream calibrate REC --stream --json -` prints), or a linear stream through the generic
 * estimator. All I/O of the port lives in the host tools.
 *
 *   mkc_replay RECORDING.csv [--window W] [--estep-every K] [--policy direction|fifo]
 *              [--init-samples N] [--checkpoints]
 *   mkc_replay --linear N M FILE.csv [--window W] [--estep-every K] [--d D] [--fp-rounds R]
 *              [--estep-max-iter I]      (a CSV with a header and columns x0..x(mn-1), y0..y(m-1))
 *   mkc_replay --read-only RECORDING.csv
 *
 * --read-only prints what the reader kept, to compare with read_recording: {"samples", "bad_rows":
 * [[line, kind], ...], "first_bad_reason", "units", "t", "mag"} (exit 0, or 2 when unreadable).
 *
 * --checkpoints adds "checkpoints": the state after every E-step checkpoint (samples seen, E-steps,
 * status, theta, sigma, d, a, normalisation, trial calibration, decision and reason).
 * Exit codes as the CLI: 0 accepted, 1 rejected, 2 usage error or unreadable input.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "mkc.h"
#include "mkc_introspect.h"
#include "recording.h"

#define EXIT_ACCEPTED 0
#define EXIT_REJECTED 1
#define EXIT_USAGE 2

static const char *QUALITY_KEYS[MKC_QUALITY] = {"residual_rms", "residual_rms_all", "norm_spread",
                                                "norm_spread_inliers", "coverage", "outlier_fraction", "condition"};

/* ---- text: a growable buffer, JSON numbers, Python's float formats ---- */

typedef struct sbuf {
    char *s;
    size_t n, cap;
} sbuf;

static void sb_put(sbuf *b, const char *txt, size_t len)
{
    if (b->n + len + 1 > b->cap) {
        size_t cap = b->cap ? b->cap : 4096;
        char *t;
        while (cap < b->n + len + 1)
            cap *= 2;
        t = (char *)realloc(b->s, cap);
        if (!t) {
            fprintf(stderr, "mkc_replay: out of memory\n");
            exit(EXIT_USAGE);
        }
        b->s = t;
        b->cap = cap;
    }
    memcpy(b->s + b->n, txt, len);
    b->n += len;
    b->s[b->n] = '\0';
}

static void sb_printf(sbuf *b, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

#include <stdarg.h>
static void sb_printf(sbuf *b, const char *fmt, ...)
{
    va_list ap;
    int k;
    char *tmp;
    va_start(ap, fmt);
    k = vsnprintf(NULL, 0, fmt, ap);
    va_end(ap);
    if (k <= 0)
        return;
    tmp = (char *)malloc((size_t)k + 1);
    if (!tmp) {
        fprintf(stderr, "mkc_replay: out of memory\n");
        exit(EXIT_USAGE);
    }
    va_start(ap, fmt);
    vsnprintf(tmp, (size_t)k + 1, fmt, ap);
    va_end(ap);
    sb_put(b, tmp, (size_t)k);
    free(tmp);
}

/* the shortest %.{p}g that reads back to the same double (a valid JSON number) */
static void shortest(char *out, size_t len, double v)
{
    int p;
    for (p = 1; p <= 17; p++) {
        snprintf(out, len, "%.*g", p, v);
        if (strtod(out, NULL) == v)
            return;
    }
}

static void json_num(sbuf *b, double v)
{
    char t[64];
    if (!isfinite(v)) {
        sb_put(b, "null", 4);
        return;
    }
    shortest(t, sizeof(t), v);
    sb_put(b, t, strlen(t));
}

/* Python's repr(float): shortest digits; fixed notation (with ".0" when integral) for
 * 1e-4 <= |v| < 1e16, else d.ddde+XX */
static void py_repr(char *out, size_t len, double v)
{
    char digits[64], *e;
    int exp10, neg = v < 0, nd, i;
    char mant[40];
    if (isnan(v)) {
        snprintf(out, len, "nan");
        return;
    }
    if (isinf(v)) {
        snprintf(out, len, neg ? "-inf" : "inf");
        return;
    }
    if (v == 0.0) {
        snprintf(out, len, signbit(v) ? "-0.0" : "0.0");
        return;
    }
    for (nd = 1; nd <= 17; nd++) {
        snprintf(digits, sizeof(digits), "%.*e", nd - 1, v);
        if (strtod(digits, NULL) == v)
            break;
    }
    e = strchr(digits, 'e');
    exp10 = atoi(e + 1);
    /* the mantissa's digits without sign and point */
    for (i = 0, nd = 0; digits + i < e; i++)
        if (digits[i] >= '0' && digits[i] <= '9')
            mant[nd++] = digits[i];
    mant[nd] = '\0';
    if (exp10 >= -4 && exp10 < 16) {
        sbuf b = {NULL, 0, 0};
        if (neg)
            sb_put(&b, "-", 1);
        if (exp10 < 0) {
            sb_put(&b, "0.", 2);
            for (i = 0; i < -exp10 - 1; i++)
                sb_put(&b, "0", 1);
            sb_put(&b, mant, (size_t)nd);
        } else if (nd <= exp10 + 1) {
            sb_put(&b, mant, (size_t)nd);
            for (i = nd; i < exp10 + 1; i++)
                sb_put(&b, "0", 1);
            sb_put(&b, ".0", 2);
        } else {
            sb_put(&b, mant, (size_t)(exp10 + 1));
            sb_put(&b, ".", 1);
            sb_put(&b, mant + exp10 + 1, (size_t)(nd - exp10 - 1));
        }
        snprintf(out, len, "%s", b.s);
        free(b.s);
    } else {
        snprintf(out, len, "%s%c%s%s%se%c%02d", neg ? "-" : "", mant[0], nd > 1 ? "." : "", nd > 1 ? mant + 1 : "",
                 "", exp10 < 0 ? '-' : '+', exp10 < 0 ? -exp10 : exp10);
    }
}

/* a JSON string; invalid UTF-8 (a unit or path from a damaged file) becomes \ufffd, as Python reads it */
static void json_str(sbuf *b, const char *s)
{
    size_t n = strlen(s), k;
    sb_put(b, "\"", 1);
    for (; *s; s += k, n -= k) {
        unsigned char c = (unsigned char)*s;
        k = 1;
        if (c == '"' || c == '\\') {
            char t[2] = {'\\', (char)c};
            sb_put(b, t, 2);
        } else if (c < 0x20 || c == 0x7f) {
            sb_printf(b, "\\u%04x", c);
        } else if (c < 0x80) {
            sb_put(b, s, 1);
        } else if (recording_u8char(s, n, &k) == 0xFFFD && !(k == 3 && memcmp(s, "\xef\xbf\xbd", 3) == 0)) {
            sb_put(b, "\\ufffd", 6);
        } else {
            sb_put(b, s, k);
        }
    }
    sb_put(b, "\"", 1);
}

/* MagCalibrator's reason strings (calib/streaming.py, calib/acceptance.py) from a reason code */
static void reason_text(sbuf *b, const mkc_mag_reason *r, const mkc_mag_rules *rules)
{
    char t1[64], t2[64], t3[64];
    int first = 1;
    switch (r->code) {
    case MKC_REASON_NONE:
        return;
    case MKC_REASON_INITIAL:
        sb_printf(b, "warming up: not enough samples yet");
        return;
    case MKC_REASON_PENDING:
        sb_printf(b, "warming up: %d/%d samples", (int)r->v[0], (int)r->v[1]);
        return;
    case MKC_REASON_WINDOW:
        sb_printf(b, "warming up: %d/%d samples in the window", (int)r->v[0], (int)r->v[1]);
        return;
    case MKC_REASON_COVERAGE_WAIT:
        sb_printf(b, "waiting for orientation coverage (%.0f%% of the sphere around a sphere fit < 40%%): rotate the "
                     "sensor through all axes", r->v[0] * 100.0);
        return;
    case MKC_REASON_MOTION_WAIT:
        sb_printf(b, "waiting for motion: the window is a cloud around one point (spread %.0f%% of its radius > 30%%), "
                     "not a sphere: rotate the sensor through all axes", r->v[0] * 100.0);
        return;
    case MKC_REASON_DEGENERATE:
        sb_printf(b, "the samples do not determine an ellipsoid (normal equations singular: they lie on a curve "
                     "or a plane): rotate the sensor through all axes");
        return;
    case MKC_REASON_NOT_FINITE:
        sb_printf(b, "trial is not an ellipsoid: ellipsoid parameters are not finite");
        return;
    case MKC_REASON_INDEFINITE:
        py_repr(t1, sizeof(t1), r->v[0]);
        py_repr(t2, sizeof(t2), r->v[1]);
        py_repr(t3, sizeof(t3), r->v[2]);
        sb_printf(b, "trial is not an ellipsoid: the fitted quadric is not an ellipsoid: A is indefinite or singular "
                     "(eigenvalues [%s, %s, %s]); the data do not cover enough orientations, or the disturbances "
                     "dominate", t1, t2, t3);
        return;
    case MKC_REASON_EMPTY:
        sb_printf(b, "trial is not an ellipsoid: the fitted quadric is an empty or imaginary ellipsoid "
                     "(1 + r0'A r0 = %.3g)", r->v[0]);
        return;
    case MKC_REASON_SINGULAR:
        sb_printf(b, "trial is not an ellipsoid: Singular matrix");
        return;
    default:
        break;
    }
#define SEP() do { if (!first) sb_put(b, "; ", 2); first = 0; } while (0)
    if (r->fails & MKC_FAIL_COVERAGE) {
        SEP();
        sb_printf(b, "sphere coverage %.0f%% < %.0f%%: rotate the sensor through more orientations", r->v[0] * 100.0,
                  (double)rules->min_coverage * 100.0);
    }
    if (r->fails & MKC_FAIL_CONDITION) {
        SEP();
        sb_printf(b, "condition number %.3g > %.3g", r->v[1], (double)rules->max_condition);
    }
    if (r->fails & MKC_FAIL_OUTLIERS) {
        SEP();
        sb_printf(b, "outlier fraction %.0f%% > %.0f%%: too much disturbance", r->v[2] * 100.0,
                  (double)rules->max_outlier_fraction * 100.0);
    }
    if (r->fails & MKC_FAIL_RESIDUAL) {
        SEP();
        sb_printf(b, "fit error %.1f%% of the field > %.0f%%", r->v[3] * 100.0, (double)rules->max_residual_rel * 100.0);
    }
    if (r->fails & MKC_FAIL_FIELD_RANGE) {
        SEP();
        sb_printf(b, "fitted field %.1f uT outside the physical range [%g, %g] uT", r->v[4], (double)rules->field_lo_ut,
                  (double)rules->field_hi_ut);
    }
    if (r->fails & MKC_FAIL_FIELD_NONPOSITIVE) {
        SEP();
        py_repr(t1, sizeof(t1), r->v[4]);
        sb_printf(b, "fitted field %s is not a positive number", t1);
    }
    if (r->fails & MKC_FAIL_DISAGREEMENT) {
        SEP();
        sb_printf(b, "not confirmed: a cold start on the same window differs by %.3g (> %.0f%% of the field); "
                     "continuing from the cold start", r->v[5], (double)rules->max_disagreement_rel * 100.0);
    }
#undef SEP
}

/* ---- the magnetometer replay ---- */

typedef struct replay {
    sbuf evolution;    /* the "evolution" list items */
    sbuf checkpoints;  /* the "checkpoints" list items */
    long nevents;
    int want_checkpoints;
} replay;

static void json_vec(sbuf *b, const double *v, int n)
{
    int i;
    sb_put(b, "[", 1);
    for (i = 0; i < n; i++) {
        if (i)
            sb_put(b, ", ", 2);
        json_num(b, v[i]);
    }
    sb_put(b, "]", 1);
}

static void json_calibration_fields(sbuf *b, const mkc_mag_calibration *c)
{
    double v[9];
    int i, j;
    for (i = 0; i < 3; i++)
        v[i] = (double)c->hard_iron[i];
    sb_printf(b, "\"hard_iron\": ");
    json_vec(b, v, 3);
    sb_printf(b, ", \"soft_iron\": [");
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++)
            v[j] = (double)c->soft_iron[i][j];
        if (i)
            sb_put(b, ", ", 2);
        json_vec(b, v, 3);
    }
    sb_printf(b, "], \"field\": ");
    json_num(b, (double)c->field);
}

static void json_quality(sbuf *b, const mkc_mag_calibration *c)
{
    int i;
    sb_put(b, "{", 1);
    for (i = 0; i < MKC_QUALITY; i++) {
        sb_printf(b, "%s\"%s\": ", i ? ", " : "", QUALITY_KEYS[i]);
        json_num(b, (double)c->quality[i]);
    }
    sb_put(b, "}", 1);
}

static void on_checkpoint(void *user, const mkc_mag_t *cal)
{
    replay *r = (replay *)user;
    const mkc_mag_event *ev = &cal->last_event;
    sbuf reason = {NULL, 0, 0};
    double v[12];
    int i, n;
    reason_text(&reason, &ev->reason, &cal->rules);
    if (r->nevents)
        sb_put(&r->evolution, ",\n    ", 6);
    sb_printf(&r->evolution, "{\"samples\": %lld, \"accepted\": %s, \"hard_iron\": ", (long long)ev->samples_seen,
              ev->accepted ? "true" : "false");
    if (ev->has_calibration) {
        for (i = 0; i < 3; i++)
            v[i] = (double)ev->hard_iron[i];
        json_vec(&r->evolution, v, 3);
        sb_printf(&r->evolution, ", \"field\": ");
        json_num(&r->evolution, (double)ev->field);
        sb_printf(&r->evolution, ", \"coverage\": ");
        json_num(&r->evolution, (double)ev->coverage);
    } else {
        sb_printf(&r->evolution, "null, \"field\": null, \"coverage\": null");
    }
    sb_printf(&r->evolution, ", \"reason\": ");
    if (reason.n)
        json_str(&r->evolution, reason.s);
    else
        sb_put(&r->evolution, "null", 4);
    sb_put(&r->evolution, "}", 1);
    if (r->want_checkpoints) {
        sbuf *b = &r->checkpoints;
        if (r->nevents)
            sb_put(b, ",\n    ", 6);
        /* esteps: E-steps done by the end of the checkpoint (a restart or cold start adds some) */
        sb_printf(b, "{\"samples\": %lld, \"esteps\": %lld, \"status\": %d, \"accepted\": %s, \"reason\": ",
                  (long long)ev->samples_seen, (long long)cal->core.counters.esteps,
                  (int)cal->core.counters.status, ev->accepted ? "true" : "false");
        json_str(b, reason.s ? reason.s : "");
        n = mkc_get(cal, 1, MKC_F_THETA, v, 12);
        sb_printf(b, ", \"theta\": ");
        json_vec(b, v, n);
        sb_printf(b, ", \"sigma\": ");
        json_num(b, (double)cal->core.sigma[0]);
        sb_printf(b, ", \"d\": ");
        json_num(b, (double)cal->core.d[0]);
        sb_printf(b, ", \"a\": ");
        json_num(b, (double)cal->core.a[0]);
        n = mkc_get(cal, 1, MKC_F_C0S0, v, 12);
        sb_printf(b, ", \"c0s0\": ");
        json_vec(b, v, n);
        sb_printf(b, ", \"trial\": ");
        if (ev->has_calibration) {
            sb_put(b, "{", 1);
            json_calibration_fields(b, &cal->trial);
            sb_printf(b, ", \"quality\": ");
            json_quality(b, &cal->trial);
            sb_put(b, "}", 1);
        } else {
            sb_put(b, "null", 4);
        }
        sb_put(b, "}", 1);
    }
    r->nevents++;
    free(reason.s);
}

static int usage(const char *msg)
{
    if (msg)
        fprintf(stderr, "mkc_replay: error: %s\n", msg);
    fprintf(stderr, "usage: mkc_replay RECORDING.csv [--window W] [--estep-every K] [--policy direction|fifo]\n"
                    "                  [--init-samples N] [--checkpoints]\n"
                    "       mkc_replay --linear N M FILE.csv [--window W] [--estep-every K] [--d D]\n"
                    "                  [--fp-rounds R] [--estep-max-iter I]\n"
                    "       mkc_replay --read-only RECORDING.csv\n");
    return EXIT_USAGE;
}

static int parse_int(const char *s, int *out)
{
    char *e;
    long v = strtol(s, &e, 10);
    if (!*s || *e || v < -1000000000L || v > 1000000000L)
        return -1;
    *out = (int)v;
    return 0;
}

/* ASCII case-insensitive equality (strcasecmp is POSIX, not C99) */
static int same_ascii_nocase(const char *a, const char *b)
{
    for (; *a && *b; a++, b++) {
        int x = (*a >= 'A' && *a <= 'Z') ? *a - 'A' + 'a' : *a, y = (*b >= 'A' && *b <= 'Z') ? *b - 'A' + 'a' : *b;
        if (x != y)
            return 0;
    }
    return *a == *b;
}

/* mkc_stream/units.py MICROTESLA, compared as Python's str.lower() does: uT, the micro sign
 * (U+00B5) or Greek mu (U+03BC) followed by T, or microtesla, in any ASCII case */
static int unit_is_ut(const char *u)
{
    return same_ascii_nocase(u, "uT") || same_ascii_nocase(u, "microtesla") || same_ascii_nocase(u, "\xc2\xb5T") ||
           same_ascii_nocase(u, "\xce\xbcT") || same_ascii_nocase(u, "\xce\x9cT");
}

static int run_mag(const char *path, int window, int K, int policy, int init_samples, int want_checkpoints)
{
    recording rec;
    static mkc_mag_t cal;              /* large with host capacities: not on the stack */
    mkc_mag_config cfg;
    replay r;
    sbuf out = {NULL, 0, 0}, reason = {NULL, 0, 0};
    mkc_mag_reason why;
    const mkc_mag_calibration *acc;
    int64_t samples, bad_frames;
    long t;
    clock_t c0, c1;
    double elapsed;
    int st;
    if (recording_read(&rec, path, 0) != 0) {
        fprintf(stderr, "mkc_replay: error: cannot read %s: %s\n", path, rec.error);
        return EXIT_USAGE;
    }
    mkc_mag_config_default(&cfg);
    cfg.stream.window = window;
    cfg.stream.estep_every = K;
    cfg.policy = policy;
    cfg.init_samples = init_samples;
    cfg.unit_ut = unit_is_ut(rec.unit);
    st = mkc_mag_init(&cal, &cfg);
    if (st != MKC_OK) {
        recording_free(&rec);
        return usage("bad configuration (window must be 9..MKC_W, init samples <= window)");
    }
    memset(&r, 0, sizeof(r));
    r.want_checkpoints = want_checkpoints;
    mkc_mag_set_listener(&cal, on_checkpoint, &r);
    c0 = clock();
    for (t = 0; t < rec.n; t++) {
        mkc_real m[3];
        m[0] = (mkc_real)rec.mag[3 * t];
        m[1] = (mkc_real)rec.mag[3 * t + 1];
        m[2] = (mkc_real)rec.mag[3 * t + 2];
        mkc_mag_push(&cal, m[0], m[1], m[2]);
    }
    c1 = clock();
    elapsed = (double)(c1 - c0) / CLOCKS_PER_SEC;
    mkc_mag_counts(&cal, &samples, &bad_frames);
    acc = mkc_mag_get_calibration(&cal, 1);
    sb_put(&out, "{\n  ", 4);
    if (acc) {
        json_calibration_fields(&out, acc);
        sb_printf(&out, ",\n  \"channels\": [{\"sigma\": ");
        json_num(&out, (double)acc->sigma);
        sb_printf(&out, ", \"d\": ");
        json_num(&out, (double)acc->d);
        sb_printf(&out, "}],\n  \"quality\": ");
        json_quality(&out, acc);
        sb_printf(&out, ",\n  \"status\": \"accepted\",\n  \"reason\": null,\n");
    } else {
        mkc_mag_status_reason(&cal, &why);
        reason_text(&reason, &why, &cal.rules);
        sb_printf(&out, "\"hard_iron\": null, \"soft_iron\": null, \"field\": null, \"channels\": [],\n  \"quality\": "
                        "{\"residual_rms\": null, \"coverage\": null, \"outlier_fraction\": null, \"condition\": null},\n"
                        "  \"status\": \"rejected\",\n  \"reason\": ");
        json_str(&out, reason.n ? reason.s : "accepted");
        sb_printf(&out, ",\n");
    }
    sb_printf(&out, "  \"counts\": {\"samples\": %ld, \"bad_frames\": %lld, \"drops\": 0, \"gaps\": %ld},\n", rec.n,
              (long long)(rec.nbad + bad_frames), recording_gaps(&rec));
    sb_printf(&out, "  \"method\": \"mkc-em-stream\",\n  \"window\": %d,\n  \"estep_every\": %d,\n", window, K);
    sb_printf(&out, "  \"first_accepted_at_sample\": ");
    if (cal.first_accepted_at >= 0)
        sb_printf(&out, "%lld", (long long)cal.first_accepted_at);
    else
        sb_put(&out, "null", 4);
    sb_printf(&out, ",\n  \"evolution\": [\n    %s\n  ],\n", r.evolution.s ? r.evolution.s : "");
    sb_printf(&out, "  \"samples_per_second\": ");
    json_num(&out, elapsed > 0 ? (double)rec.n / elapsed : HUGE_VAL);
    sb_printf(&out, ",\n  \"units\": {\"mag\": ");
    json_str(&out, rec.unit);
    sb_printf(&out, "},\n  \"recording\": ");
    json_str(&out, path);
    sb_printf(&out, ",\n  \"implementation\": \"firmware_ref C99 (%s)\"", sizeof(mkc_real) == 8 ? "double" : "float");
    if (want_checkpoints)
        sb_printf(&out, ",\n  \"checkpoints\": [\n    %s\n  ]", r.checkpoints.s ? r.checkpoints.s : "");
    sb_printf(&out, "\n}\n");
    fputs(out.s, stdout);
    if (rec.nbad)
        fprintf(stderr, "mkc_replay: %ld bad rows skipped (first: line %ld, %s)\n", rec.nbad, rec.first_bad_line,
                rec.first_bad_reason);
    free(out.s);
    free(reason.s);
    free(r.evolution.s);
    free(r.checkpoints.s);
    recording_free(&rec);
    return acc ? EXIT_ACCEPTED : EXIT_REJECTED;
}

/* ---- the reader alone (tests/test_hostile_c.py compares it with read_recording) ---- */

static int run_read_only(const char *path)
{
    recording rec;
    sbuf head = {NULL, 0, 0};
    long i;
    if (recording_read(&rec, path, 1) != 0) {
        fprintf(stderr, "mkc_replay: error: cannot read %s: %s\n", path, rec.error);
        return EXIT_USAGE;
    }
    /* %.17g: exact round trip (kept values are finite); printed directly, a recording may be large */
    printf("{\"samples\": %ld, \"bad_rows\": [", rec.n);
    for (i = 0; i < rec.nbad; i++)
        printf("%s[%ld, \"%s\"]", i ? ", " : "", rec.bad_line[i], rec_kind_names[rec.bad_kind[i]]);
    sb_printf(&head, "],\n \"first_bad_reason\": ");
    json_str(&head, rec.nbad ? rec.first_bad_reason : "");
    sb_printf(&head, ",\n \"units\": {\"mag\": ");
    json_str(&head, rec.unit);
    fputs(head.s, stdout);
    printf("},\n \"t\": [");
    for (i = 0; i < rec.n; i++)
        printf("%s%.17g", i ? ", " : "", rec.t[i]);
    printf("],\n \"mag\": [");
    for (i = 0; i < rec.n; i++)
        printf("%s[%.17g, %.17g, %.17g]", i ? ", " : "", rec.mag[3 * i], rec.mag[3 * i + 1], rec.mag[3 * i + 2]);
    printf("]}\n");
    free(head.s);
    recording_free(&rec);
    return EXIT_ACCEPTED;
}

/* ---- the generic stream: a CSV of x0..x(mn-1), y0..y(m-1) per row (header line first) ---- */

static int run_linear(const char *path, int n, int m, int window, int K, double d0, int fp_rounds, int es_iter)
{
    static mkc_stream_t st;
    mkc_config cfg;
    FILE *f = fopen(path, "r");
    char line[65536];
    mkc_real x[MKC_N * MKC_M], y[MKC_M], dd[MKC_M];
    long k = 0;
    int first = 1, i, r;
    double v[MKC_N + MKC_M];
    if (!f) {
        fprintf(stderr, "mkc_replay: error: cannot open %s\n", path);
        return EXIT_USAGE;
    }
    if (n < 1 || m < 1 || n > MKC_N || m > MKC_M) {
        fclose(f);
        return usage("--linear N M outside the compiled capacity");
    }
    mkc_config_default(&cfg, n, m);
    cfg.window = window;
    cfg.estep_every = K;
    if (fp_rounds >= 0)
        cfg.fp_rounds = fp_rounds;
    if (es_iter >= 0)
        cfg.estep_max_iter = es_iter;
    for (i = 0; i < m; i++)
        dd[i] = (mkc_real)d0;
    if (mkc_stream_init(&st, &cfg, NULL, d0 > 0 ? dd : NULL, NULL) != MKC_OK) {
        fclose(f);
        return usage("bad configuration");
    }
    printf("{\"checkpoints\": [");
    if (!fgets(line, sizeof(line), f)) {   /* header */
        fclose(f);
        printf("]}\n");
        return EXIT_USAGE;
    }
    while (fgets(line, sizeof(line), f)) {
        char *p = line, *e;
        int64_t e0 = st.core.counters.esteps;
        for (i = 0; i < m * n + m; i++) {
            double val = strtod(p, &e);
            if (e == p)
                val = (double)NAN;
            if (i < m * n)
                x[i] = (mkc_real)val;
            else
                y[i - m * n] = (mkc_real)val;
            p = strchr(e, ',');
            if (!p)
                p = e;
            else
                p++;
        }
        r = mkc_stream_learn_one(&st, x, y, -1);
        if (st.core.counters.esteps > e0) {
            int nn;
            printf("%s\n  {\"index\": %ld, \"status\": %d, \"theta\": [", first ? "" : ",", k, r);
            nn = mkc_get(&st, 0, MKC_F_THETA, v, MKC_N + MKC_M);
            for (i = 0; i < nn; i++)
                printf("%s%.17g", i ? ", " : "", v[i]);
            printf("], \"sigma\": [");
            nn = mkc_get(&st, 0, MKC_F_SIGMA, v, MKC_N + MKC_M);
            for (i = 0; i < nn; i++)
                printf("%s%.17g", i ? ", " : "", v[i]);
            printf("], \"d\": [");
            nn = mkc_get(&st, 0, MKC_F_D, v, MKC_N + MKC_M);
            for (i = 0; i < nn; i++)
                printf("%s%.17g", i ? ", " : "", v[i]);
            printf("]}");
            first = 0;
        }
        k++;
    }
    printf("\n]}\n");
    fclose(f);
    return EXIT_ACCEPTED;
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    int window = 512, K = 32, policy = MKC_POLICY_DIRECTION, init_samples = 0, want = 0, i;
    int linear = 0, read_only = 0, n = 0, m = 0, fp_rounds = -1, es_iter = -1;
    double d0 = -1.0;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--window") == 0 && i + 1 < argc) {
            if (parse_int(argv[++i], &window) != 0)
                return usage("--window needs an integer");
        } else if (strcmp(a, "--estep-every") == 0 && i + 1 < argc) {
            if (parse_int(argv[++i], &K) != 0)
                return usage("--estep-every needs an integer");
        } else if (strcmp(a, "--init-samples") == 0 && i + 1 < argc) {
            if (parse_int(argv[++i], &init_samples) != 0)
                return usage("--init-samples needs an integer");
        } else if (strcmp(a, "--policy") == 0 && i + 1 < argc) {
            const char *p = argv[++i];
            if (strcmp(p, "direction") == 0)
                policy = MKC_POLICY_DIRECTION;
            else if (strcmp(p, "fifo") == 0)
                policy = MKC_POLICY_FIFO;
            else
                return usage("--policy is direction or fifo");
        } else if (strcmp(a, "--fp-rounds") == 0 && i + 1 < argc) {
            if (parse_int(argv[++i], &fp_rounds) != 0)
                return usage("--fp-rounds needs an integer");
        } else if (strcmp(a, "--estep-max-iter") == 0 && i + 1 < argc) {
            if (parse_int(argv[++i], &es_iter) != 0)
                return usage("--estep-max-iter needs an integer");
        } else if (strcmp(a, "--d") == 0 && i + 1 < argc) {
            d0 = strtod(argv[++i], NULL);
        } else if (strcmp(a, "--checkpoints") == 0) {
            want = 1;
        } else if (strcmp(a, "--read-only") == 0) {
            read_only = 1;
        } else if (strcmp(a, "--linear") == 0 && i + 2 < argc) {
            linear = 1;
            if (parse_int(argv[++i], &n) != 0 || parse_int(argv[++i], &m) != 0)
                return usage("--linear N M needs two integers");
        } else if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) {
            usage(NULL);
            return EXIT_ACCEPTED;
        } else if (a[0] == '-' && a[1]) {
            return usage("unknown option");
        } else if (!path) {
            path = a;
        } else {
            return usage("one recording at a time");
        }
    }
    if (!path)
        return usage("no recording given");
    if (read_only)
        return run_read_only(path);
    if (window < 16 && !linear)
        return usage("--window must be >= 16");
    if (window > MKC_W)
        return usage("--window is larger than the compiled capacity MKC_W");
    if (K < 1)
        return usage("--estep-every must be >= 1");
    if (linear)
        return run_linear(path, n, m, window, K, d0, fp_rounds, es_iter);
    return run_mag(path, window, K, policy, init_samples, want);
}
