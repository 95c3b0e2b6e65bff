/* footprint_base_main.c: footprint_main.c without the calibrator: the same reset, vectors, sensor
 * loop and outputs, the raw sample copied where the calibrated one would go. Its text subtracted
 * from footprint_main.c's is the flash the library adds to a firmware (its code and constants and
 * the libm, libc and libgcc functions it pulls in); tools/bench_firmware_target.py reports both. */
#include <stdint.h>

#include "mkc_config.h"      /* mkc_real: the sample type of the build */

static volatile mkc_real sensor[3];
static volatile int32_t sensor_samples;
static volatile mkc_real calibrated[3];
static volatile int32_t accepted;

int main(void)
{
    mkc_real raw[3];
    int32_t k;
    for (k = 0; k < sensor_samples; k++) {
        raw[0] = sensor[0];
        raw[1] = sensor[1];
        raw[2] = sensor[2];
        calibrated[0] = raw[0];
        calibrated[1] = raw[1];
        calibrated[2] = raw[2];
    }
    accepted = 0;
    return 0;
}
