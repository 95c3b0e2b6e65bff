/* main.c: calibrate a synthetic stream with the mkc library, save and restore the calibration, and
 * print what the build is (precision and window as this program's mkc.h sees them and as the library
 * set them up: they must agree). Exit 0 when a calibration was accepted and restored unchanged. */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "mkc.h"
#include "mkc_persist.h"

static mkc_mag_t cal, restored;

int main(void)
{
    const double b_true[3] = {10.0, -20.0, 5.0}, s_true[3] = {1.10, 0.90, 1.00};
    uint8_t saved[MKC_PERSIST_CALIBRATION_BYTES];
    uint32_t lcg = 12345u;
    mkc_mag_config cfg;
    mkc_real probe[3] = {(mkc_real)40.0, (mkc_real)-5.0, (mkc_real)12.0}, o1[3], o2[3];
    size_t n;
    long k;
    int load, same;

    mkc_mag_config_default(&cfg);
    if (mkc_mag_init(&cal, &cfg) != MKC_OK || mkc_mag_init(&restored, &cfg) != MKC_OK)
        return 2;
    /* a pole-to-pole spiral of a 50 uT field (uT) through the soft and hard iron, with +-0.2 uT noise */
    for (k = 0; k < 8000; k++) {
        double s = (double)(k % 2000) / 2000.0, z = cos(6.283185307179586 * s);
        double phi = 6.283185307179586 * 17.0 * s, r = sqrt(1.0 - z * z), u[3], m[3];
        int i;
        u[0] = r * cos(phi);
        u[1] = r * sin(phi);
        u[2] = z;
        for (i = 0; i < 3; i++) {
            lcg = lcg * 1664525u + 1013904223u;
            m[i] = 50.0 * s_true[i] * u[i] + b_true[i] + 0.4 * ((double)(lcg >> 8) / 16777216.0 - 0.5);
        }
        mkc_mag_push(&cal, (mkc_real)m[0], (mkc_real)m[1], (mkc_real)m[2]);
    }
    n = mkc_persist_save_calibration(&cal, saved, sizeof saved);
    load = mkc_persist_load_calibration(&restored, saved, n);
    same = mkc_mag_apply(&cal, probe, o1) == MKC_OK && mkc_mag_apply(&restored, probe, o2) == MKC_OK &&
           memcmp(o1, o2, sizeof o1) == 0;
    printf("real_bytes=%u acc_double=%d estep_double=%d capacity=%d window=%d state_bytes=%lu "
           "accepted=%d b=%.4f,%.4f,%.4f field=%.4f saved=%lu load=%d same=%d\n",
           (unsigned)sizeof(mkc_real), MKC_ACC_DOUBLE, MKC_ESTEP_DOUBLE, MKC_W, (int)cal.core.cfg.window,
           (unsigned long)sizeof cal, (int)cal.accepted.valid, (double)cal.accepted.hard_iron[0],
           (double)cal.accepted.hard_iron[1], (double)cal.accepted.hard_iron[2], (double)cal.accepted.field,
           (unsigned long)n, load, same);
    return cal.accepted.valid && load == MKC_PERSIST_OK && same ? 0 : 1;
}
