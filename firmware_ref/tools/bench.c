/* bench: throughput of the C port on this machine (compiled with the firmware capacities of
 * mkc_config.h: n = 9, m = 1, W = 256 unless overridden), for the README's footprint/speed table.
 *
 *   stream  mkc_stream_learn_many on ellipsoid features (random directions, so every window is
 *           well-posed; what tools/bench_stream.py times for Numba's learn_many), 10% bursts
 *   mag     mkc_mag_push_many on raw samples in hand-held sweep order (direction window, trial and
 *           accepted calibrations, acceptance predicate, cold-start confirmation)
 *   E-step  one E-step + rebuild on the full window (kernels' estep_window + rebuild), alone
 * Times are the best of 3 (wall clock, CLOCK_MONOTONIC when POSIX has it, else clock()).
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "../src/mkc_internal.h"
#include "synth.h"

static double now(void)
{
#if defined(CLOCK_MONOTONIC)
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
#else
    return (double)clock() / CLOCKS_PER_SEC;
#endif
}

static mkc_stream_t st, st_copy;
static mkc_mag_t cal;

int main(int argc, char **argv)
{
    long T = 400000, Tm = 200000, k, warm;
    int W = MKC_W, K = MKC_K, rep, i;
    double *raw, *rawm, best = 1e300, bestm = 1e300, t0, es, c0[3] = {0.0, 0.0, 0.0}, s0 = 0.0;
    mkc_real *X, *Y, *M;
    mkc_config cfg;
    mkc_mag_config mcfg;
    if (argc > 1)
        T = atol(argv[1]);
    raw = (double *)malloc((size_t)T * 3 * sizeof(double));
    rawm = (double *)malloc((size_t)Tm * 3 * sizeof(double));
    X = (mkc_real *)malloc((size_t)T * 9 * sizeof(mkc_real));
    Y = (mkc_real *)malloc((size_t)T * sizeof(mkc_real));
    M = (mkc_real *)malloc((size_t)Tm * 3 * sizeof(mkc_real));
    if (!raw || !rawm || !X || !Y || !M)
        return 2;
    synth_mag(raw, T, 0, 0.1, 1);
    synth_mag(rawm, Tm, 1, 0.1, 2);
    /* normalisation of the features: mean and rms radius of the first 2000 samples */
    for (k = 0; k < 2000; k++)
        for (i = 0; i < 3; i++)
            c0[i] += raw[3 * k + i] / 2000.0;
    for (k = 0; k < 2000; k++) {
        double d0 = raw[3 * k] - c0[0], d1 = raw[3 * k + 1] - c0[1], d2 = raw[3 * k + 2] - c0[2];
        s0 += (d0 * d0 + d1 * d1 + d2 * d2) / 2000.0;
    }
    s0 = sqrt(s0);
    for (k = 0; k < T; k++) {
        double x = (raw[3 * k] - c0[0]) / s0, y = (raw[3 * k + 1] - c0[1]) / s0, z = (raw[3 * k + 2] - c0[2]) / s0;
        mkc_real *r = X + 9 * k;
        r[0] = (mkc_real)(x * x);
        r[1] = (mkc_real)(y * y);
        r[2] = (mkc_real)(z * z);
        r[3] = (mkc_real)(x * y);
        r[4] = (mkc_real)(x * z);
        r[5] = (mkc_real)(y * z);
        r[6] = (mkc_real)x;
        r[7] = (mkc_real)y;
        r[8] = (mkc_real)z;
        Y[k] = RC(1.0);
    }
    for (k = 0; k < 3 * Tm; k++)
        M[k] = (mkc_real)rawm[k];
    mkc_config_default(&cfg, 9, 1);
    cfg.window = W;
    cfg.estep_every = K;
    warm = 2L * W;
    for (rep = 0; rep < 3; rep++) {
        double dt;
        mkc_stream_init(&st, &cfg, NULL, NULL, NULL);
        mkc_stream_learn_many(&st, X, Y, warm, NULL);
        t0 = now();
        mkc_stream_learn_many(&st, X + 9 * warm, Y + warm, T - warm, NULL);
        dt = now() - t0;
        best = dt < best ? dt : best;
    }
    /* one E-step + rebuild on the full window, repeated on a copy (as bench_stream.py estep_cost) */
    st_copy = st;
    t0 = now();
    for (rep = 0; rep < 2000; rep++) {
        mkc__estep_window(&st_copy.core);
        mkc__rebuild(&st_copy.core);
    }
    es = (now() - t0) / 2000.0;
    mkc_mag_config_default(&mcfg);
    mcfg.stream.window = W;
    mcfg.stream.estep_every = K;
    for (rep = 0; rep < 3; rep++) {
        double dt;
        mkc_mag_init(&cal, &mcfg);
        mkc_mag_push_many(&cal, M, 4L * W, NULL);
        t0 = now();
        mkc_mag_push_many(&cal, M + 3 * 4L * W, Tm - 4L * W, NULL);
        dt = now() - t0;
        bestm = dt < bestm ? dt : bestm;
    }
    printf("mkc C port (%s, sizeof(mkc_real) = %d, acc %d, E-step %d), n = 9, m = 1, W = %d, K = %d\n",
           sizeof(mkc_real) == 8 ? "double" : "float", (int)sizeof(mkc_real), (int)sizeof(mkc_acc),
           (int)sizeof(mkc_ereal), W, K);
    printf("  stream learn_many : %12.0f samples/s  (%.3f us/sample; restarts %lld, singular %lld, Cholesky/sample %.3f)\n",
           (double)(T - warm) / best, 1e6 * best / (double)(T - warm), (long long)st.core.counters.restarts,
           (long long)st.core.counters.singular,
           (double)st.core.counters.factors / (double)st.core.counters.seen);
    printf("  E-step + rebuild  : %12.2f us (full window, alone)\n", 1e6 * es);
    printf("  mag push_many     : %12.0f samples/s  (%.3f us/sample; checkpoints %lld, accepted: %s)\n",
           (double)(Tm - 4L * W) / bestm, 1e6 * bestm / (double)(Tm - 4L * W), (long long)cal.checkpoints,
           cal.accepted.valid ? "yes" : "no");
    printf("  sizeof: mkc_stream_t %lu bytes, mkc_mag_t %lu bytes\n", (unsigned long)sizeof(mkc_stream_t),
           (unsigned long)sizeof(mkc_mag_t));
    free(raw);
    free(rawm);
    free(X);
    free(Y);
    free(M);
    return 0;
}
