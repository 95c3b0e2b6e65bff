/* Arduino.h: the few Arduino core calls live_calibration.ino uses, for compiling and running the
 * sketch on the host (tests/test_firmware_package.py). Serial writes to stdout, the clock is a
 * simulated 32-bit microsecond counter the runner sets, EEPROM is an array (EEPROM.h). */
#ifndef MKC_ARDUINO_SHIM_H
#define MKC_ARDUINO_SHIM_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>

class ShimSerial {
public:
    void begin(unsigned long) {}
    size_t write(const uint8_t *p, size_t n) { return fwrite(p, 1, n, stdout); }
    size_t write(uint8_t b) { return write(&b, 1); }
    size_t print(const char *s) { return (size_t)fputs(s, stdout); }
    size_t print(long v) { return (size_t)printf("%ld", v); }
    size_t print(int v) { return print((long)v); }
    size_t print(double v, int digits = 2) { return (size_t)printf("%.*f", digits, v); }
    size_t println(const char *s) { return print(s) + print("\r\n"); }
};
extern ShimSerial Serial;

/* the simulated clock: microseconds since "boot", wrapping at 2^32 as on the boards */
extern uint64_t shim_clock_us;
inline unsigned long micros() { return (unsigned long)(uint32_t)shim_clock_us; }
inline unsigned long millis() { return (unsigned long)(uint32_t)(shim_clock_us / 1000u); }
inline void delay(unsigned long ms) { shim_clock_us += 1000u * (uint64_t)ms; }

void setup();
void loop();

#endif
