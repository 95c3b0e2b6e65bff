// live_calibration: calibrate a magnetometer on the board, live, and keep the calibration across resets.
//
// Every sample from readMagnetometer() (below: REPLACE IT with your sensor's driver) is
//   - fed to the streaming calibrator (mkc_mag_push),
//   - corrected with the accepted calibration once there is one (mkc_mag_apply: m = S (raw - b)),
//   - sent over Serial as a frame of mkc's binary protocol (MAG_F32: sync, seq, device time, CRC-16),
//     so the host can watch and record it:  mkc-stream live --port /dev/ttyACM0 --baud 115200 --protocol binary
// A newly accepted calibration is saved to EEPROM (flash emulation on ESP32/RP2040) with mkc_persist's
// CRC-protected layout and restored at the next boot, so the board starts calibrated.
//
// Serial carries either the binary frames (TEXT_REPORT 0, for mkc-stream) or readable text lines for
// the Serial Monitor (TEXT_REPORT 1): the calibration when accepted and the corrected field. Text
// printed in setup(), before the first frame, is skipped by the host's decoder as lead-in bytes.
//
// Memory: the calibrator is one static struct, 22 KiB with the library's defaults (double, window 256);
// 9 KiB with -DMKC_USE_FLOAT -DMKC_W=128 (PlatformIO: build_flags). A board with 2 KiB of RAM
// (Arduino Uno) cannot hold it.
#include <Arduino.h>
#include <EEPROM.h>
#include <math.h>
#include <string.h>

#include "mkc.h"
#include "mkc_persist.h"

#ifndef TEXT_REPORT
#define TEXT_REPORT 0              // 0: binary frames on Serial (mkc-stream live); 1: text lines
#endif
#define SERIAL_BAUD 115200
#define EEPROM_ADDRESS 0           // where the saved calibration starts (MKC_PERSIST_CALIBRATION_BYTES long)
#define SAVE_INTERVAL_MS 600000UL  // save an updated calibration at most every 10 minutes (flash wear)
#define SAVE_CHANGE 0.01f          // ... and only when it moved by more than 1% of the field (or 0.01 in S)
#define REPORT_EVERY 50            // TEXT_REPORT 1: print the corrected field every N samples

// ---- the sensor: REPLACE THIS with your magnetometer's driver ------------------------------------
// Return true with the field in microtesla (sensor axes) when a new sample is ready, false otherwise.
// This placeholder has no sensor and never returns a sample. For an I2C part (QMC5883L, LIS3MDL,
// MMC5983MA, ...) read its data registers with Wire and scale counts to uT with the datasheet's
// sensitivity for the range you configured. (It is weak so that the host test can supply samples.)
static bool sensorIsPlaceholder = false;
__attribute__((weak)) bool readMagnetometer(float uT[3])
{
    (void)uT;
    sensorIsPlaceholder = true;
    return false;
}

// ---- mkc's binary frame (docs/live-and-recording.md, "The binary protocol, byte by byte") ----------
static const uint8_t FRAME_VERSION = 1, FRAME_MAG_F32 = 1;

// CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor
static uint16_t crc16(const uint8_t *p, size_t n)
{
    uint16_t crc = 0xFFFF;
    for (size_t k = 0; k < n; k++) {
        crc ^= (uint16_t)(p[k] << 8);
        for (int bit = 0; bit < 8; bit++)
            crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
    }
    return crc;
}

static uint8_t *putLE(uint8_t *p, uint32_t v, int bytes)
{
    for (int k = 0; k < bytes; k++)
        *p++ = (uint8_t)(v >> (8 * k));
    return p;
}

// sync A5 5A, version << 4 | type, length 12, seq (uint16), time (uint32 us), mx my mz (float32), CRC-16
static void sendFrame(uint16_t seq, uint32_t tUs, const float uT[3])
{
    uint8_t f[24], *p = f;
    *p++ = 0xA5;
    *p++ = 0x5A;
    *p++ = (uint8_t)(FRAME_VERSION << 4 | FRAME_MAG_F32);
    *p++ = 12;
    p = putLE(p, seq, 2);
    p = putLE(p, tUs, 4);
    for (int i = 0; i < 3; i++) {
        uint32_t bits;
        memcpy(&bits, &uT[i], 4);           // IEEE-754 single, sent little-endian whatever the CPU
        p = putLE(p, bits, 4);
    }
    p = putLE(p, crc16(f + 2, (size_t)(p - f - 2)), 2);
    Serial.write(f, (size_t)(p - f));
}

// ---- the calibrator and its saved copy ------------------------------------------------------------
static mkc_mag_t cal;                       // static: far too large for the stack
static mkc_mag_calibration lastSaved;       // what EEPROM holds (valid = 0: nothing)
static unsigned long lastSaveMs;
static mkc_mag_calibration lastSeen;        // the accepted calibration last looked at
static uint16_t seq;
static long samples;

static void printCalibration(const char *what, const mkc_mag_calibration *c)
{
    Serial.print(what);
    Serial.print(": b = [");
    for (int i = 0; i < 3; i++) {
        Serial.print((double)c->hard_iron[i], 6);
        Serial.print(i < 2 ? ", " : "] uT, F = ");
    }
    Serial.print((double)c->field, 6);
    Serial.print(" uT, S = [");
    for (int i = 0; i < 9; i++) {
        Serial.print((double)c->soft_iron[i / 3][i % 3], 6);
        Serial.print(i < 8 ? ", " : "]\n");
    }
}

static void eepromBegin()
{
#if defined(ESP8266) || defined(ESP32) || defined(ARDUINO_ARCH_RP2040)
    EEPROM.begin(EEPROM_ADDRESS + MKC_PERSIST_CALIBRATION_BYTES);   // flash emulation: a RAM copy
#endif
}

static void eepromCommit()
{
#if defined(ESP8266) || defined(ESP32) || defined(ARDUINO_ARCH_RP2040)
    EEPROM.commit();
#endif
}

static void restoreCalibration()
{
    uint8_t buf[MKC_PERSIST_CALIBRATION_BYTES];
    for (size_t k = 0; k < sizeof buf; k++)
        buf[k] = EEPROM.read((int)(EEPROM_ADDRESS + k));
    int st = mkc_persist_load_calibration(&cal, buf, sizeof buf);
    if (st == MKC_PERSIST_OK) {
        lastSaved = lastSeen = cal.accepted;
        printCalibration("restored from EEPROM", &cal.accepted);
    } else {
        Serial.print("no calibration restored: ");
        Serial.print(mkc_persist_error_text(st));
        Serial.print("\n");
    }
}

static float maxChange(const mkc_mag_calibration *a, const mkc_mag_calibration *b)
{
    float F = (float)b->field, m = fabsf((float)(a->field - b->field)) / F;
    for (int i = 0; i < 3; i++) {
        float d = fabsf((float)(a->hard_iron[i] - b->hard_iron[i])) / F;
        m = d > m ? d : m;
    }
    for (int i = 0; i < 9; i++) {
        float d = fabsf((float)(a->soft_iron[i / 3][i % 3] - b->soft_iron[i / 3][i % 3]));
        m = d > m ? d : m;
    }
    return m;
}

static bool sameCalibration(const mkc_mag_calibration *a, const mkc_mag_calibration *b)
{
    return a->samples_seen == b->samples_seen && a->esteps == b->esteps && a->field == b->field &&
           memcmp(a->hard_iron, b->hard_iron, sizeof a->hard_iron) == 0;
}

// A calibration the calibrator has newly accepted: save it when it differs from the saved one (the
// first one at once, later ones at most every SAVE_INTERVAL_MS).
static void maybeSave()
{
    const mkc_mag_calibration *acc = mkc_mag_get_calibration(&cal, 1);
    if (!acc || (lastSeen.valid && sameCalibration(acc, &lastSeen)))
        return;
    lastSeen = *acc;
    if (TEXT_REPORT)
        printCalibration("accepted", acc);
    if (lastSaved.valid && (maxChange(acc, &lastSaved) <= SAVE_CHANGE || millis() - lastSaveMs < SAVE_INTERVAL_MS))
        return;
    uint8_t buf[MKC_PERSIST_CALIBRATION_BYTES];
    size_t n = mkc_persist_save_calibration(&cal, buf, sizeof buf);
    for (size_t k = 0; k < n; k++) {
        int addr = (int)(EEPROM_ADDRESS + k);
        if (EEPROM.read(addr) != buf[k])     // write only the bytes that changed (EEPROM wear)
            EEPROM.write(addr, buf[k]);
    }
    eepromCommit();
    lastSaved = *acc;
    lastSaveMs = millis();
    if (TEXT_REPORT) {
        Serial.print("saved to EEPROM: ");
        Serial.print((long)n);
        Serial.print(" bytes\n");
    }
}

void setup()
{
    Serial.begin(SERIAL_BAUD);
    eepromBegin();
    mkc_mag_config cfg;
    mkc_mag_config_default(&cfg);            // samples in uT: the physical field range is checked
    mkc_mag_init(&cal, &cfg);
    restoreCalibration();
}

void loop()
{
    float uT[3];
    if (!readMagnetometer(uT)) {
        static bool warned = false;
        if (sensorIsPlaceholder && !warned) {
            Serial.print("readMagnetometer() is a placeholder: replace it with your sensor's driver\n");
            warned = true;
        }
        return;
    }
    if (!TEXT_REPORT)
        sendFrame(seq++, (uint32_t)micros(), uT);
    mkc_mag_push(&cal, uT[0], uT[1], uT[2]);  // MKC_REJECTED for NaN/inf: skipped and counted
    samples++;
    maybeSave();
    mkc_real raw[3] = {uT[0], uT[1], uT[2]}, m[3];
    if (mkc_mag_apply(&cal, raw, m) == MKC_OK) {
        // m is the corrected field in uT: use it here (heading, field checks, ...)
        if (TEXT_REPORT && samples % REPORT_EVERY == 0) {
            Serial.print("corrected: ");
            for (int i = 0; i < 3; i++) {
                Serial.print((double)m[i], 3);
                Serial.print(i < 2 ? " " : " uT\n");
            }
        }
    }
}
