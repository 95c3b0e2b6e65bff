/* footprint_main.c: the smallest firmware that uses the calibrator, for arm-none-eabi-size: the
 * state (static), the configuration, a sample loop (mkc_mag_push) and the calibrated output
 * (mkc_mag_apply, mkc_mag_get_calibration), with startup.c's reset and vectors. The samples come
 * from a volatile "sensor register", so the compiler keeps every call; the loop runs
 * `sensor_samples` times (0 as linked), so the program also runs to a clean exit in qemu.
 * tools/bench_firmware_target.py reports its text (code and constants), data and bss. */
#include "mkc.h"

static mkc_mag_t cal;
static volatile mkc_real sensor[3];
static volatile int32_t sensor_samples;
static volatile mkc_real calibrated[3];
static volatile int32_t accepted;

int main(void)
{
    mkc_mag_config cfg;
    mkc_real raw[3], out[3];
    int32_t k;
    mkc_mag_config_default(&cfg);
    if (mkc_mag_init(&cal, &cfg) != MKC_OK)
        return 2;
    for (k = 0; k < sensor_samples; k++) {
        raw[0] = sensor[0];
        raw[1] = sensor[1];
        raw[2] = sensor[2];
        (void)mkc_mag_push(&cal, raw[0], raw[1], raw[2]);
        if (mkc_mag_apply(&cal, raw, out) == MKC_OK) {
            calibrated[0] = out[0];
            calibrated[1] = out[1];
            calibrated[2] = out[2];
        }
    }
    accepted = mkc_mag_get_calibration(&cal, 1) != NULL;
    return 0;
}
