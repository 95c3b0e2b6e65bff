/* EEPROM.h: an EEPROM of SHIM_EEPROM_BYTES bytes in RAM, erased to 0xFF; the runner loads and saves
 * it from a file between runs, so a second run sees what the first one wrote (a reset). */
#ifndef MKC_EEPROM_SHIM_H
#define MKC_EEPROM_SHIM_H

#include <stdint.h>

#define SHIM_EEPROM_BYTES 1024

class ShimEEPROM {
public:
    uint8_t bytes[SHIM_EEPROM_BYTES];
    long writes = 0;                      /* bytes written, to check that unchanged bytes are not */
    uint8_t read(int addr) const { return addr >= 0 && addr < SHIM_EEPROM_BYTES ? bytes[addr] : 0xFF; }
    void write(int addr, uint8_t v)
    {
        if (addr >= 0 && addr < SHIM_EEPROM_BYTES) {
            bytes[addr] = v;
            writes++;
        }
    }
    int length() const { return SHIM_EEPROM_BYTES; }
    void begin(int) {}
    bool commit() { return true; }
};
extern ShimEEPROM EEPROM;

#endif
