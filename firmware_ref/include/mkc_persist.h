/* mkc_persist.h: save the accepted calibration to bytes and restore it after a reset (EEPROM, flash).
 *
 * Layout version 1, every field little-endian whatever the CPU (written byte by byte):
 *
 *   offset  size  field
 *   0       4     magic "MKCC" (0x4D 0x4B 0x43 0x43)
 *   4       1     layout version (1)
 *   5       1     precision tag: bytes of mkc_real (8 double build, 4 float builds)
 *   6       2     payload length L, uint16 (192 double, 104 float)
 *   8       L     payload: 22 mkc_real as IEEE-754 (hard_iron b[3]; soft_iron S[3][3] row by row;
 *                 field F; sigma; d; quality[MKC_QUALITY]), then samples_seen and esteps as int64
 *   8+L     4     CRC-32 (ISO-HDLC, as zlib.crc32: reflected poly 0xEDB88320, init and final xor
 *                 0xFFFFFFFF) over bytes 0 .. 7+L
 *
 * A restored calibration becomes the accepted one and is applied at once (mkc_mag_apply). Only the
 * calibration is restored, not the window or the switching pool: with the default pooled switching
 * (MKC_SWITCH_POOLED) the first trial of this run that passes the acceptance predicate replaces it;
 * with MKC_SWITCH_PAIRED a trial replaces it only when the window supports the trial over it.
 */
#ifndef MKC_PERSIST_H
#define MKC_PERSIST_H

#include <stddef.h>
#include <stdint.h>

#include "mkc.h"

#ifdef __cplusplus
extern "C" {
#endif

#define MKC_PERSIST_VERSION 1
#define MKC_PERSIST_REALS (3 + 9 + 3 + MKC_QUALITY)   /* b, S, F, sigma, d, quality */
#define MKC_PERSIST_HEADER_BYTES 8
#define MKC_PERSIST_PAYLOAD_BYTES (MKC_PERSIST_REALS * sizeof(mkc_real) + 2 * 8)
/* Bytes of a saved calibration in this build: 204 (double), 116 (float). */
#define MKC_PERSIST_CALIBRATION_BYTES (MKC_PERSIST_HEADER_BYTES + MKC_PERSIST_PAYLOAD_BYTES + 4)

/* Results of mkc_persist_load_calibration; the header is checked first, so the code names the first
 * thing wrong. Numbered apart from the kernel status codes (MKC_OK .. MKC_NOT_CALIBRATED). */
enum {
    MKC_PERSIST_OK = 0,
    MKC_PERSIST_BAD_ARGUMENT = 16, /* NULL pointer, or the calibrator was not initialised */
    MKC_PERSIST_SHORT = 17,        /* fewer bytes than the header or the layout needs */
    MKC_PERSIST_BAD_MAGIC = 18,    /* not a saved calibration (e.g. erased EEPROM: 0xFF) */
    MKC_PERSIST_BAD_VERSION = 19,  /* a layout version this build does not read */
    MKC_PERSIST_BAD_CONFIG = 20,   /* saved by a build of another precision (double vs float) */
    MKC_PERSIST_BAD_CRC = 21,      /* the bytes were damaged */
    MKC_PERSIST_BAD_VALUE = 22     /* CRC good but a value is not finite or the field is not > 0 */
};

/* Write the ACCEPTED calibration into buf; returns the bytes written (MKC_PERSIST_CALIBRATION_BYTES),
 * or 0 when there is no accepted calibration yet, cap is too small or a pointer is NULL. */
size_t mkc_persist_save_calibration(const mkc_mag_t *cal, uint8_t *buf, size_t cap);

/* Restore a saved calibration into an initialised calibrator (mkc_mag_init) as its accepted one.
 * Returns MKC_PERSIST_OK or an error code above; on any error the calibrator is not changed. */
int mkc_persist_load_calibration(mkc_mag_t *cal, const uint8_t *buf, size_t len);

/* A short English text for a code above (for a log line). */
const char *mkc_persist_error_text(int code);

/* CRC-32 (ISO-HDLC) of n bytes, continuing from crc (start with 0): the layout's checksum. */
uint32_t mkc_persist_crc32(uint32_t crc, const uint8_t *data, size_t n);

#ifdef __cplusplus
}
#endif

#endif /* MKC_PERSIST_H */
