/* shim_main.cpp: run an Arduino sketch on the host. Environment:
 *   MKC_SHIM_SAMPLES  CSV of "t_us,mx,my,mz" (t_us: the board's microsecond clock, uT as float32);
 *                     each row is one readMagnetometer() sample, the clock set to t_us first
 *   MKC_SHIM_EEPROM   file holding the EEPROM: read before setup() (absent: erased, 0xFF), written
 *                     after the last sample
 * setup(), then loop() until the samples are used up. stdout carries what the sketch wrote to Serial;
 * stderr gets one line "shim: samples N eeprom_writes W". */
#include <stdlib.h>
#include <string.h>

#include "Arduino.h"
#include "EEPROM.h"

ShimSerial Serial;
ShimEEPROM EEPROM;
uint64_t shim_clock_us;

static FILE *samples_file;
static bool samples_done;
static long samples_read;

/* the sketch's sensor, replacing its weak placeholder */
bool readMagnetometer(float uT[3])
{
    char line[256];
    unsigned long long t_us;
    while (samples_file && fgets(line, sizeof line, samples_file)) {
        if (sscanf(line, "%llu,%f,%f,%f", &t_us, &uT[0], &uT[1], &uT[2]) == 4) {
            shim_clock_us = t_us;
            samples_read++;
            return true;
        }
    }
    samples_done = true;
    return false;
}

int main()
{
    const char *path = getenv("MKC_SHIM_SAMPLES"), *eeprom = getenv("MKC_SHIM_EEPROM");
    memset(EEPROM.bytes, 0xFF, sizeof EEPROM.bytes);
    if (eeprom) {
        FILE *f = fopen(eeprom, "rb");
        if (f) {
            size_t got = fread(EEPROM.bytes, 1, sizeof EEPROM.bytes, f);
            (void)got;
            fclose(f);
        }
    }
    samples_file = path ? fopen(path, "r") : NULL;
    if (!samples_file) {
        fprintf(stderr, "shim: cannot open MKC_SHIM_SAMPLES '%s'\n", path ? path : "");
        return 2;
    }
    setup();
    while (!samples_done)
        loop();
    fclose(samples_file);
    fflush(stdout);
    if (eeprom) {
        FILE *f = fopen(eeprom, "wb");
        if (!f || fwrite(EEPROM.bytes, 1, sizeof EEPROM.bytes, f) != sizeof EEPROM.bytes) {
            fprintf(stderr, "shim: cannot write MKC_SHIM_EEPROM '%s'\n", eeprom);
            return 2;
        }
        fclose(f);
    }
    fprintf(stderr, "shim: samples %ld eeprom_writes %ld\n", samples_read, EEPROM.writes);
    return 0;
}
