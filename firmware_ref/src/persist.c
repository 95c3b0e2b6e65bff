/* persist.c: the accepted calibration to and from a fixed little-endian byte layout with a CRC-32
 * (layout in mkc_persist.h). Values are written byte by byte from their IEEE-754 bit patterns, so
 * the bytes are the same on every CPU; a build reads only what a build of its precision wrote. */
#include <math.h>

#include "mkc_internal.h"
#include "mkc_persist.h"

#ifdef MKC_USE_FLOAT
typedef uint32_t real_uint;
#else
typedef uint64_t real_uint;
#endif
typedef union { mkc_real r; real_uint u; } real_bits;   /* C99 reads a union member as the other's bits */

uint32_t mkc_persist_crc32(uint32_t crc, const uint8_t *data, size_t n)
{
    size_t k;
    int bit;
    crc = ~crc;
    for (k = 0; k < n; k++) {
        crc ^= data[k];
        for (bit = 0; bit < 8; bit++)     /* bitwise: no 1 KiB table in flash */
            crc = (crc & 1u) ? (crc >> 1) ^ 0xEDB88320u : crc >> 1;
    }
    return ~crc;
}

static uint8_t *put_u64(uint8_t *p, uint64_t v)
{
    int k;
    for (k = 0; k < 8; k++)
        *p++ = (uint8_t)(v >> (8 * k));
    return p;
}

static uint64_t get_u64(const uint8_t *p, int bytes)
{
    uint64_t v = 0;
    int k;
    for (k = 0; k < bytes; k++)
        v |= (uint64_t)p[k] << (8 * k);
    return v;
}

static uint8_t *put_real(uint8_t *p, mkc_real r)
{
    real_bits b;
    int k;
    b.r = r;
    for (k = 0; k < (int)sizeof(mkc_real); k++)
        *p++ = (uint8_t)(b.u >> (8 * k));
    return p;
}

static mkc_real get_real(const uint8_t *p)
{
    real_bits b;
    b.u = (real_uint)get_u64(p, (int)sizeof(mkc_real));
    return b.r;
}

/* The calibration's reals in layout order. */
static void gather(const mkc_mag_calibration *c, mkc_real *v)
{
    int j, k, i = 0;
    for (j = 0; j < 3; j++)
        v[i++] = c->hard_iron[j];
    for (j = 0; j < 3; j++)
        for (k = 0; k < 3; k++)
            v[i++] = c->soft_iron[j][k];
    v[i++] = c->field;
    v[i++] = c->sigma;
    v[i++] = c->d;
    for (j = 0; j < MKC_QUALITY; j++)
        v[i++] = c->quality[j];
}

static void scatter(mkc_mag_calibration *c, const mkc_real *v)
{
    int j, k, i = 0;
    for (j = 0; j < 3; j++)
        c->hard_iron[j] = v[i++];
    for (j = 0; j < 3; j++)
        for (k = 0; k < 3; k++)
            c->soft_iron[j][k] = v[i++];
    c->field = v[i++];
    c->sigma = v[i++];
    c->d = v[i++];
    for (j = 0; j < MKC_QUALITY; j++)
        c->quality[j] = v[i++];
}

size_t mkc_persist_save_calibration(const mkc_mag_t *cal, uint8_t *buf, size_t cap)
{
    mkc_real v[MKC_PERSIST_REALS];
    uint8_t *p = buf;
    uint32_t crc;
    size_t payload = MKC_PERSIST_PAYLOAD_BYTES;
    int k;
    if (!cal || !buf || cap < MKC_PERSIST_CALIBRATION_BYTES || !cal->accepted.valid)
        return 0;
    *p++ = 'M';
    *p++ = 'K';
    *p++ = 'C';
    *p++ = 'C';
    *p++ = MKC_PERSIST_VERSION;
    *p++ = (uint8_t)sizeof(mkc_real);
    *p++ = (uint8_t)(payload & 0xFFu);
    *p++ = (uint8_t)(payload >> 8);
    gather(&cal->accepted, v);
    for (k = 0; k < MKC_PERSIST_REALS; k++)
        p = put_real(p, v[k]);
    p = put_u64(p, (uint64_t)cal->accepted.samples_seen);
    p = put_u64(p, (uint64_t)cal->accepted.esteps);
    crc = mkc_persist_crc32(0, buf, (size_t)(p - buf));
    for (k = 0; k < 4; k++)
        *p++ = (uint8_t)(crc >> (8 * k));
    return (size_t)(p - buf);
}

int mkc_persist_load_calibration(mkc_mag_t *cal, const uint8_t *buf, size_t len)
{
    mkc_real v[MKC_PERSIST_REALS];
    mkc_mag_calibration c;
    const uint8_t *p;
    size_t body, k;
    int j;
    if (!cal || !buf || cal->core.cfg.n != 9)     /* mkc_mag_init sets n = 9; a zeroed state has 0 */
        return MKC_PERSIST_BAD_ARGUMENT;
    if (len < MKC_PERSIST_HEADER_BYTES)
        return MKC_PERSIST_SHORT;
    if (buf[0] != 'M' || buf[1] != 'K' || buf[2] != 'C' || buf[3] != 'C')
        return MKC_PERSIST_BAD_MAGIC;
    if (buf[4] != MKC_PERSIST_VERSION)
        return MKC_PERSIST_BAD_VERSION;
    if (buf[5] != sizeof(mkc_real) || ((size_t)buf[6] | (size_t)buf[7] << 8) != MKC_PERSIST_PAYLOAD_BYTES)
        return MKC_PERSIST_BAD_CONFIG;
    if (len < MKC_PERSIST_CALIBRATION_BYTES)
        return MKC_PERSIST_SHORT;
    body = MKC_PERSIST_HEADER_BYTES + MKC_PERSIST_PAYLOAD_BYTES;
    if (mkc_persist_crc32(0, buf, body) != (uint32_t)get_u64(buf + body, 4))
        return MKC_PERSIST_BAD_CRC;
    p = buf + MKC_PERSIST_HEADER_BYTES;
    for (k = 0; k < MKC_PERSIST_REALS; k++, p += sizeof(mkc_real)) {
        v[k] = get_real(p);
        if (!isfinite(v[k]))
            return MKC_PERSIST_BAD_VALUE;
    }
    /* c starts from a copy so that every member (padding aside) is defined */
    c = cal->accepted;
    scatter(&c, v);
    if (!(c.field > 0))
        return MKC_PERSIST_BAD_VALUE;
    c.samples_seen = (int64_t)get_u64(p, 8);
    c.esteps = (int64_t)get_u64(p + 8, 8);
    c.valid = 1;
    c.accepted = 1;
    c.reason.code = MKC_REASON_NONE;
    c.reason.fails = 0;
    for (j = 0; j < 6; j++)
        c.reason.v[j] = 0;
    cal->accepted = c;
    mkc__seed_pool(cal);      /* new trials are weighed against it, as against one the run accepted */
    return MKC_PERSIST_OK;
}

const char *mkc_persist_error_text(int code)
{
    switch (code) {
    case MKC_PERSIST_OK: return "ok";
    case MKC_PERSIST_BAD_ARGUMENT: return "bad argument (NULL, or calibrator not initialised)";
    case MKC_PERSIST_SHORT: return "too few bytes";
    case MKC_PERSIST_BAD_MAGIC: return "no saved calibration (magic)";
    case MKC_PERSIST_BAD_VERSION: return "unknown layout version";
    case MKC_PERSIST_BAD_CONFIG: return "saved by a build of another precision";
    case MKC_PERSIST_BAD_CRC: return "damaged (CRC mismatch)";
    case MKC_PERSIST_BAD_VALUE: return "value not finite or field not positive";
    default: return "unknown code";
    }
}
