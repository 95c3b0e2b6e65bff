/* synth.h: deterministic synthetic magnetometer data for the C-only tools (bench, self-test).
 * A field of 50 uT seen through a known soft iron and hard iron, plus noise and optional bursts;
 * xorshift64* random numbers, so every build and platform sees the same stream. Header-only. */
#ifndef MKC_SYNTH_H
#define MKC_SYNTH_H

#include <math.h>
#include <stdint.h>

typedef struct synth_rng {
    uint64_t s;
} synth_rng;

static double synth_uniform(synth_rng *r)
{
    r->s ^= r->s >> 12;
    r->s ^= r->s << 25;
    r->s ^= r->s >> 27;
    return (double)((r->s * 2685821657736338717ULL) >> 11) * (1.0 / 9007199254740992.0);
}

static double synth_normal(synth_rng *r)
{
    double u = synth_uniform(r), v = synth_uniform(r);
    if (u < 1e-300)
        u = 1e-300;
    return sqrt(-2.0 * log(u)) * cos(6.283185307179586 * v);
}

static const double SYNTH_B[3] = {12.0, -25.0, 7.5};
static const double SYNTH_SINV[3][3] = {{1.10, 0.05, -0.02}, {0.05, 0.92, 0.03}, {-0.02, 0.03, 0.99}};

/* T samples into m (T x 3). sweep: 1 = slow pole-to-pole spiral (hand-held order), 0 = random
 * directions (every window covers the sphere). burst_fraction of the samples get a 5-40 uT offset
 * in bursts of 40. */
static void synth_mag(double *m, long T, int sweep, double burst_fraction, uint64_t seed)
{
    synth_rng r;
    long k;
    double off[3] = {0.0, 0.0, 0.0};
    long burst_left = 0;
    r.s = seed * 0x9E3779B97F4A7C15ULL + 1;
    for (k = 0; k < T; k++) {
        double u[3], nrm, v[3];
        int i;
        if (sweep) {
            double s = (double)(k % 4000) / 4000.0, z = cos(3.141592653589793 * 2.0 * s);
            double phi = 6.283185307179586 * 27.0 * s + 0.3 * (double)(k / 4000), rr = sqrt(1.0 - z * z);
            u[0] = rr * cos(phi) + 0.02 * synth_normal(&r);
            u[1] = rr * sin(phi) + 0.02 * synth_normal(&r);
            u[2] = z + 0.02 * synth_normal(&r);
        } else {
            u[0] = synth_normal(&r);
            u[1] = synth_normal(&r);
            u[2] = synth_normal(&r);
        }
        nrm = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
        for (i = 0; i < 3; i++)
            u[i] = 50.0 * u[i] / nrm;
        if (burst_left == 0 && synth_uniform(&r) < burst_fraction / 40.0) {
            double mag = 5.0 + 35.0 * synth_uniform(&r), d[3], dn;
            d[0] = synth_normal(&r);
            d[1] = synth_normal(&r);
            d[2] = synth_normal(&r);
            dn = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            for (i = 0; i < 3; i++)
                off[i] = mag * d[i] / dn;
            burst_left = 40;
        }
        for (i = 0; i < 3; i++)
            v[i] = SYNTH_SINV[i][0] * u[0] + SYNTH_SINV[i][1] * u[1] + SYNTH_SINV[i][2] * u[2] + SYNTH_B[i] +
                   0.3 * synth_normal(&r) + (burst_left > 0 ? off[i] : 0.0);
        if (burst_left > 0)
            burst_left--;
        m[3 * k] = v[0];
        m[3 * k + 1] = v[1];
        m[3 * k + 2] = v[2];
    }
}

#endif
