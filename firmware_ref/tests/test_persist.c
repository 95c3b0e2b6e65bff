/* test_persist.c: saving and restoring the accepted calibration (mkc_persist.h).
 *
 * A deterministic synthetic stream (tools/synth.h) is calibrated; the accepted calibration is saved,
 * every refusal is provoked (short buffer, magic, version, precision tag, payload length, a flipped
 * bit in each byte, a non-finite value under a good CRC, NULL and an uninitialised state) and must
 * leave the target state byte for byte unchanged; then the bytes are restored into a fresh
 * calibrator and the calibration must equal the saved one bit for bit and apply identically.
 * With an argument, the saved bytes are also written to that file (tests/test_firmware_package.py
 * decodes them with zlib and struct, an independent reading of the layout). Exit 0: all passed.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "mkc.h"
#include "mkc_persist.h"
#include "../tools/synth.h"

static int failures;

#define CHECK(cond, what)                                                           \
    do {                                                                            \
        if (!(cond)) {                                                              \
            fprintf(stderr, "FAIL %s:%d: %s\n", __FILE__, __LINE__, (what));        \
            failures++;                                                             \
        }                                                                           \
    } while (0)

static mkc_mag_t cal, fresh, probe;

/* load damaged bytes into a calibrated copy: the expected code, and the state not touched */
static void expect_refusal(const uint8_t *bytes, size_t len, int code, const char *what)
{
    int got;
    memcpy(&probe, &cal, sizeof cal);
    got = mkc_persist_load_calibration(&probe, bytes, len);
    if (got != code) {
        fprintf(stderr, "FAIL %s: code %d (%s), expected %d\n", what, got, mkc_persist_error_text(got), code);
        failures++;
    }
    CHECK(memcmp(&probe, &cal, sizeof cal) == 0, what);
}

/* the CRC of a modified buffer recomputed, so that the check behind it is the one that fires */
static void reseal(uint8_t *b, size_t n)
{
    uint32_t crc = mkc_persist_crc32(0, b, n - 4);
    int k;
    for (k = 0; k < 4; k++)
        b[n - 4 + (size_t)k] = (uint8_t)(crc >> (8 * k));
}

int main(int argc, char **argv)
{
    enum { T = 6000 };
    static double mags[3 * T];
    uint8_t saved[MKC_PERSIST_CALIBRATION_BYTES + 16], bad[sizeof saved];
    mkc_mag_config cfg;
    const mkc_mag_calibration *a, *r;
    size_t n, k;
    long t;
    int bit;
    const uint8_t check[] = "123456789";

    /* the layout's CRC is zlib's: check value of CRC-32/ISO-HDLC */
    CHECK(mkc_persist_crc32(0, check, 9) == 0xCBF43926u, "crc32 check value");

    mkc_mag_config_default(&cfg);
    CHECK(mkc_mag_init(&cal, &cfg) == MKC_OK, "init");
    CHECK(mkc_persist_save_calibration(&cal, saved, sizeof saved) == 0, "nothing to save before acceptance");
    synth_mag(mags, T, 1, 0.0, 11);
    for (t = 0; t < T; t++)
        mkc_mag_push(&cal, (mkc_real)mags[3 * t], (mkc_real)mags[3 * t + 1], (mkc_real)mags[3 * t + 2]);
    a = mkc_mag_get_calibration(&cal, 1);
    CHECK(a != NULL && cal.accepted.valid, "a calibration was accepted");
    if (!cal.accepted.valid)
        return 1;

    CHECK(mkc_persist_save_calibration(&cal, saved, MKC_PERSIST_CALIBRATION_BYTES - 1) == 0, "save: cap too small");
    CHECK(mkc_persist_save_calibration(NULL, saved, sizeof saved) == 0, "save: NULL state");
    n = mkc_persist_save_calibration(&cal, saved, sizeof saved);
    CHECK(n == MKC_PERSIST_CALIBRATION_BYTES, "save: bytes written");
    CHECK(n == (sizeof(mkc_real) == 8 ? 204u : 116u), "save: documented size");

    /* refusals, each leaving the state as it was */
    expect_refusal(saved, 0, MKC_PERSIST_SHORT, "empty buffer");
    expect_refusal(saved, 7, MKC_PERSIST_SHORT, "header cut");
    expect_refusal(saved, n - 1, MKC_PERSIST_SHORT, "CRC cut");
    memset(bad, 0xFF, sizeof bad);
    expect_refusal(bad, n, MKC_PERSIST_BAD_MAGIC, "erased EEPROM");
    memcpy(bad, saved, n);
    bad[4] = 2;
    reseal(bad, n);
    expect_refusal(bad, n, MKC_PERSIST_BAD_VERSION, "version 2");
    memcpy(bad, saved, n);
    bad[5] = (uint8_t)(sizeof(mkc_real) == 8 ? 4 : 8);
    reseal(bad, n);
    expect_refusal(bad, n, MKC_PERSIST_BAD_CONFIG, "other precision");
    memcpy(bad, saved, n);
    bad[6] = (uint8_t)(bad[6] + 1);
    reseal(bad, n);
    expect_refusal(bad, n, MKC_PERSIST_BAD_CONFIG, "payload length");
    /* one flipped bit anywhere in the payload or the CRC: a CRC-32 catches every single-bit error */
    for (k = 8; k < n; k++) {
        for (bit = 0; bit < 8; bit += 3) {
            memcpy(bad, saved, n);
            bad[k] = (uint8_t)(bad[k] ^ (1u << bit));
            expect_refusal(bad, n, MKC_PERSIST_BAD_CRC, "flipped bit");
        }
    }
    memcpy(bad, saved, n);
    for (k = 0; k < sizeof(mkc_real); k++)           /* hard_iron[0] = NaN (all ones), resealed */
        bad[8 + k] = 0xFF;
    reseal(bad, n);
    expect_refusal(bad, n, MKC_PERSIST_BAD_VALUE, "NaN under a good CRC");
    memcpy(bad, saved, n);
    for (k = 0; k < sizeof(mkc_real); k++)           /* field = +0 */
        bad[8 + 12 * sizeof(mkc_real) + k] = 0;
    reseal(bad, n);
    expect_refusal(bad, n, MKC_PERSIST_BAD_VALUE, "zero field under a good CRC");
    expect_refusal(NULL, n, MKC_PERSIST_BAD_ARGUMENT, "NULL bytes");
    memset(&probe, 0, sizeof probe);
    CHECK(mkc_persist_load_calibration(&probe, saved, n) == MKC_PERSIST_BAD_ARGUMENT, "uninitialised state");

    /* restore after a "reset": a fresh calibrator applies the saved calibration at once */
    CHECK(mkc_mag_init(&fresh, &cfg) == MKC_OK, "fresh init");
    {
        mkc_real raw[3] = {(mkc_real)30.0, (mkc_real)-12.5, (mkc_real)41.0}, o1[3], o2[3];
        CHECK(mkc_mag_apply(&fresh, raw, o2) == MKC_NOT_CALIBRATED, "fresh: not calibrated");
        CHECK(mkc_persist_load_calibration(&fresh, saved, n) == MKC_PERSIST_OK, "restore");
        r = mkc_mag_get_calibration(&fresh, 1);
        CHECK(r != NULL, "restored calibration present");
        if (r) {
            CHECK(memcmp(r->hard_iron, a->hard_iron, sizeof a->hard_iron) == 0, "b bit for bit");
            CHECK(memcmp(r->soft_iron, a->soft_iron, sizeof a->soft_iron) == 0, "S bit for bit");
            CHECK(memcmp(&r->field, &a->field, sizeof a->field) == 0, "F bit for bit");
            CHECK(memcmp(&r->sigma, &a->sigma, sizeof a->sigma) == 0, "sigma bit for bit");
            CHECK(memcmp(&r->d, &a->d, sizeof a->d) == 0, "d bit for bit");
            CHECK(memcmp(r->quality, a->quality, sizeof a->quality) == 0, "quality bit for bit");
            CHECK(r->samples_seen == a->samples_seen && r->esteps == a->esteps, "provenance");
            CHECK(r->valid == 1 && r->accepted == 1 && r->reason.code == MKC_REASON_NONE, "flags");
        }
        CHECK(mkc_mag_apply(&cal, raw, o1) == MKC_OK && mkc_mag_apply(&fresh, raw, o2) == MKC_OK, "apply");
        CHECK(memcmp(o1, o2, sizeof o1) == 0, "restored applies identically");
        /* saving the restored calibration gives the same bytes */
        CHECK(mkc_persist_save_calibration(&fresh, bad, sizeof bad) == n && memcmp(bad, saved, n) == 0,
              "save after restore: same bytes");
        /* the restored calibrator keeps calibrating: feed the stream again */
        for (t = 0; t < T; t++)
            mkc_mag_push(&fresh, (mkc_real)mags[3 * t], (mkc_real)mags[3 * t + 1], (mkc_real)mags[3 * t + 2]);
        CHECK(fresh.accepted.valid && fresh.core.counters.esteps > 0, "calibrates on after restore");
    }

    if (argc > 1) {
        FILE *f = fopen(argv[1], "wb");
        CHECK(f != NULL && fwrite(saved, 1, n, f) == n, "write the saved bytes");
        if (f)
            fclose(f);
    }
    printf("test_persist (%s): %lu bytes, b = [%.9g %.9g %.9g], F = %.9g: %s\n",
           sizeof(mkc_real) == 8 ? "double" : "float", (unsigned long)n, (double)a->hard_iron[0],
           (double)a->hard_iron[1], (double)a->hard_iron[2], (double)a->field, failures ? "FAILED" : "ok");
    return failures ? 1 : 0;
}
