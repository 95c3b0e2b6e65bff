/* recording.c: the recording CSV reader of the host tools (rules in recording.h).
 *
 * Every line and cell is a (pointer, length) extent of the file buffer, never a C string, so a NUL
 * byte is data (Python keeps reading after it) and no pass rescans what an earlier one read.
 */
#include "recording.h"

#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

const char *const rec_kind_names[REC_NKINDS] = {"non-numeric", "missing", "non-finite", "cell count",
                                                "truncated", "t decreasing", "unexpected comment"};

static const char *const REQ[4] = {"t", "mx", "my", "mz"};

#define ECHO_MAX 80   /* characters of the file a message echoes (a 50 MB line must not reach stderr) */
#define CELL_ECHO 40  /* read_recording shows 40 characters of a non-numeric cell */

/* ---- the text as Python decodes it: bytes.decode("utf-8", "replace") ---- */

/* The code point at p (0xFFFD for an invalid sequence) and its byte length. An invalid sequence
 * ends before the first byte that cannot continue it (Python's "maximal subpart" rule), so an ASCII
 * byte (',' or '\n') is never swallowed by one. */
unsigned long recording_u8char(const char *p, size_t n, size_t *len)
{
    const unsigned char *s = (const unsigned char *)p;
    unsigned char lo = 0x80, hi = 0xBF;
    unsigned long cp;
    size_t need, k;
    if (s[0] < 0x80) {
        *len = 1;
        return s[0];
    }
    if (s[0] >= 0xC2 && s[0] <= 0xDF) {
        need = 1;
        cp = s[0] & 0x1Fu;
    } else if (s[0] >= 0xE0 && s[0] <= 0xEF) {
        need = 2;
        cp = s[0] & 0x0Fu;
        if (s[0] == 0xE0)
            lo = 0xA0;          /* no overlong forms */
        else if (s[0] == 0xED)
            hi = 0x9F;          /* no surrogates */
    } else if (s[0] >= 0xF0 && s[0] <= 0xF4) {
        need = 3;
        cp = s[0] & 0x07u;
        if (s[0] == 0xF0)
            lo = 0x90;
        else if (s[0] == 0xF4)
            hi = 0x8F;          /* nothing above U+10FFFF */
    } else {
        *len = 1;
        return 0xFFFD;
    }
    for (k = 1; k <= need; k++) {
        if (k >= n || s[k] < lo || s[k] > hi) {
            *len = k;
            return 0xFFFD;
        }
        cp = (cp << 6) | (s[k] & 0x3Fu);
        lo = 0x80;
        hi = 0xBF;
    }
    *len = need + 1;
    return cp;
}

/* Python's str.isspace */
static int py_space(unsigned long c)
{
    return (c >= 0x09 && c <= 0x0D) || (c >= 0x1C && c <= 0x20) || c == 0x85 || c == 0xA0 || c == 0x1680 ||
           (c >= 0x2000 && c <= 0x200A) || c == 0x2028 || c == 0x2029 || c == 0x202F || c == 0x205F || c == 0x3000;
}

/* the value of a Unicode decimal digit (category Nd, which float() accepts), else -1 */
static int py_decimal(unsigned long c)
{
    /* the digit zeros of Unicode 14.0 (Python 3.11's unicodedata); each starts a run 0..9 */
    static const unsigned long zero[] = {
        0x30, 0x660, 0x6F0, 0x7C0, 0x966, 0x9E6, 0xA66, 0xAE6, 0xB66, 0xBE6, 0xC66, 0xCE6, 0xD66, 0xDE6, 0xE50, 0xED0,
        0xF20, 0x1040, 0x1090, 0x17E0, 0x1810, 0x1946, 0x19D0, 0x1A80, 0x1A90, 0x1B50, 0x1BB0, 0x1C40, 0x1C50, 0xA620,
        0xA8D0, 0xA900, 0xA9D0, 0xA9F0, 0xAA50, 0xABF0, 0xFF10, 0x104A0, 0x10D30, 0x11066, 0x110F0, 0x11136, 0x111D0,
        0x112F0, 0x11450, 0x114D0, 0x11650, 0x116C0, 0x11730, 0x118E0, 0x11950, 0x11C50, 0x11D50, 0x11DA0, 0x16A60,
        0x16AC0, 0x16B50, 0x1D7CE, 0x1D7D8, 0x1D7E2, 0x1D7EC, 0x1D7F6, 0x1E140, 0x1E2F0, 0x1E950, 0x1FBF0};
    size_t lo = 0, hi = sizeof(zero) / sizeof(zero[0]);
    while (lo < hi) {           /* the number of zeros <= c */
        size_t mid = (lo + hi) / 2;
        if (zero[mid] <= c)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo && c - zero[lo - 1] < 10 ? (int)(c - zero[lo - 1]) : -1;
}

static unsigned long next_char(const char *p, const char *end, size_t *len)
{
    if ((unsigned char)*p < 0x80) {
        *len = 1;
        return (unsigned char)*p;
    }
    return recording_u8char(p, (size_t)(end - p), len);
}

/* the first non-whitespace character of [p, end), or end */
static const char *skip_space(const char *p, const char *end)
{
    size_t k;
    while (p < end && py_space(next_char(p, end, &k)))
        p += k;
    return p;
}

/* str.strip() of the extent [*p, *p + *n) */
static void strip(const char **p, size_t *n)
{
    const char *end = *p + *n, *s = skip_space(*p, end), *last = s;
    size_t k;
    *p = s;
    while (s < end) {
        unsigned long c = next_char(s, end, &k);
        s += k;
        if (!py_space(c))
            last = s;
    }
    *n = (size_t)(last - *p);
}

/* at most max characters of [p, p + n) for a message, bytes outside printable ASCII as \xHH */
static void echo(char *out, size_t cap, const char *p, size_t n, size_t max)
{
    size_t o = 0, i;
    for (i = 0; i < n && i < max && o + 8 < cap; i++) {
        unsigned char c = (unsigned char)p[i];
        if (c >= 0x20 && c < 0x7F && c != '\\' && c != '\'') {
            out[o++] = (char)c;
        } else {
            snprintf(out + o, cap - o, "\\x%02x", c);
            o += 4;
        }
    }
    if (i < n && o + 4 <= cap) {
        memcpy(out + o, "...", 3);
        o += 3;
    }
    out[o] = '\0';
}

/* ---- numbers: Python's float(str) ---- */

typedef struct scratch {
    char *s;
    size_t cap;
} scratch;

static int is_digit(char c)
{
    return c >= '0' && c <= '9';
}

static int ascii_space(char c)
{
    return c == ' ' || (c >= '\t' && c <= '\r');
}

/* case-insensitive: does [p, end) start with word (lower case)? */
static int starts_with(const char *p, const char *end, const char *word)
{
    for (; *word; word++, p++)
        if (p >= end || (*p | 0x20) != *word)
            return 0;
    return 1;
}

/* float() of a stripped, non-empty cell, step by step as CPython's PyFloat_FromString: 0 with *v, or
 * -1 when it is not a number. */
static int py_float(scratch *sc, const char *p, size_t n, double *v)
{
    char *b, *s, *e, *q;
    size_t i, o = 0, j, k;
    int d;
    if (n + 1 > sc->cap) {
        char *t = (char *)realloc(sc->s, n + 1);
        if (!t)
            return -2;
        sc->s = t;
        sc->cap = n + 1;
    }
    b = sc->s;
    /* non-ASCII: whitespace becomes ' ', a decimal digit its ASCII digit, anything else fails */
    for (i = 0; i < n; i += k) {
        unsigned long c = next_char(p + i, p + n, &k);
        if (c == 0)
            return -1;
        if (c < 0x80)
            b[o++] = (char)c;
        else if (py_space(c))
            b[o++] = ' ';
        else if ((d = py_decimal(c)) >= 0)
            b[o++] = (char)('0' + d);
        else
            return -1;
    }
    /* '_' only between two digits, then dropped */
    for (i = 0, j = 0; i < o; i++) {
        if (b[i] == '_') {
            if (!(i > 0 && is_digit(b[i - 1]) && i + 1 < o && is_digit(b[i + 1])))
                return -1;
        } else {
            b[j++] = b[i];
        }
    }
    s = b;
    e = b + j;
    while (s < e && ascii_space(*s))
        s++;
    while (e > s + 1 && ascii_space(e[-1]))
        e--;
    /* the whole extent must be one number: [sign] digits [. digits] [e [sign] digits], inf, infinity, nan */
    q = s + (s < e && (*s == '+' || *s == '-'));
    k = 0;
    while (q < e && is_digit(*q))
        q++, k++;
    if (q < e && *q == '.') {
        q++;
        while (q < e && is_digit(*q))
            q++, k++;
    }
    if (!k) {
        q = s + (s < e && (*s == '+' || *s == '-'));
        if (starts_with(q, e, "inf")) {
            q += 3;
            if (starts_with(q, e, "inity"))
                q += 5;
            if (q != e)
                return -1;
            *v = *s == '-' ? -HUGE_VAL : HUGE_VAL;
            return 0;
        }
        if (starts_with(q, e, "nan") && q + 3 == e) {
            *v = (double)NAN;
            return 0;
        }
        return -1;
    }
    if (q < e && (*q == 'e' || *q == 'E')) {
        char *x = q + 1;
        if (x < e && (*x == '+' || *x == '-'))
            x++;
        if (x < e && is_digit(*x)) {
            while (x < e && is_digit(*x))
                x++;
            q = x;
        }
    }
    if (q != e)
        return -1;
    *e = '\0';
    *v = strtod(s, NULL);       /* the C locale; correctly rounded as Python's own strtod */
    return 0;
}

/* ---- the reader ---- */

typedef struct name {
    const char *p;
    size_t n;
} name;

/* column names in Python's sorted() order: by decoded code points */
static int name_cmp(const void *a, const void *b)
{
    const name *x = *(const name *const *)a, *y = *(const name *const *)b;
    const char *p = x->p, *pe = x->p + x->n, *q = y->p, *qe = y->p + y->n;
    size_t kp, kq;
    while (p < pe && q < qe) {
        unsigned long cp = next_char(p, pe, &kp), cq = next_char(q, qe, &kq);
        if (cp != cq)
            return cp < cq ? -1 : 1;
        p += kp;
        q += kq;
    }
    return (p < pe) - (q < qe);
}

typedef struct reader {
    recording *rec;
    const char *path;
    int keep_bad;
    name *names;
    long ncol, col[4];
    scratch sc;
    double tmax;
    int have_t;
} reader;

static int add_row(recording *rec, double t, const double *m)
{
    if (rec->n == rec->cap) {
        long cap = rec->cap ? 2 * rec->cap : 4096;
        double *tt = (double *)realloc(rec->t, (size_t)cap * sizeof(double)), *mm;
        if (!tt)
            return -1;
        rec->t = tt;
        mm = (double *)realloc(rec->mag, (size_t)cap * 3 * sizeof(double));
        if (!mm)
            return -1;
        rec->mag = mm;
        rec->cap = cap;
    }
    rec->t[rec->n] = t;
    memcpy(rec->mag + 3 * rec->n, m, 3 * sizeof(double));
    rec->n++;
    return 0;
}

static int add_bad(reader *r, long line, int kind)
{
    recording *rec = r->rec;
    if (r->keep_bad) {
        if (rec->nbad == rec->badcap) {
            long cap = rec->badcap ? 2 * rec->badcap : 256;
            long *l = (long *)realloc(rec->bad_line, (size_t)cap * sizeof(long));
            unsigned char *k;
            if (!l)
                return -1;
            rec->bad_line = l;
            k = (unsigned char *)realloc(rec->bad_kind, (size_t)cap);
            if (!k)
                return -1;
            rec->bad_kind = k;
            rec->badcap = cap;
        }
        rec->bad_line[rec->nbad] = line;
        rec->bad_kind[rec->nbad] = (unsigned char)kind;
    }
    if (!rec->nbad)
        rec->first_bad_line = line;
    rec->nbad++;
    return 0;
}

/* One data row [p, p + n) at file line `line`; is_last: the cut-off last line of the file. Only the
 * first bad row's reason is formatted (a file of bad rows costs no text per row). -1: out of memory. */
static int read_row(reader *r, const char *p, size_t n, long line, int is_last)
{
    recording *rec = r->rec;
    const char *end = p + n, *s = skip_space(p, end), *c;
    char why[720] = "", e1[ECHO_MAX * 4 + 8], e2[CELL_ECHO * 4 + 8];
    double req[4] = {0.0, 0.0, 0.0, 0.0};
    int kind = -1, first = rec->nbad == 0;
    long j, k;
    if (s == end)
        return 0;               /* blank */
    if (*s == '#') {
        kind = REC_COMMENT;
        if (first)
            snprintf(why, sizeof(why), "unexpected comment: comment line after the header");
    } else {
        long cells = 1;
        for (c = p; (c = (const char *)memchr(c, ',', (size_t)(end - c))) != NULL; c++)
            cells++;
        if (cells != r->ncol) {
            kind = REC_CELL_COUNT;
            if (first)
                snprintf(why, sizeof(why), "cell count: expected %ld cells, got %ld", r->ncol, cells);
        } else {
            for (j = 0, c = p; j < r->ncol; j++) {
                const char *ce = (const char *)memchr(c, ',', (size_t)(end - c)), *cs = c;
                size_t cn;
                double v = (double)NAN;
                int bad;
                if (!ce)
                    ce = end;
                cn = (size_t)(ce - c);
                strip(&cs, &cn);
                bad = cn ? py_float(&r->sc, cs, cn, &v) : 0;
                if (bad == -2)
                    return -1;
                if (bad) {
                    kind = REC_NON_NUMERIC;
                    if (first) {
                        echo(e1, sizeof(e1), r->names[j].p, r->names[j].n, ECHO_MAX);
                        echo(e2, sizeof(e2), cs, cn, CELL_ECHO);
                        snprintf(why, sizeof(why), "non-numeric: column '%s' has '%s'", e1, e2);
                    }
                    break;
                }
                for (k = 0; k < 4; k++)
                    if (r->col[k] == j)
                        req[k] = v;
                c = ce + 1;
            }
        }
    }
    if (kind >= 0 && is_last) {
        kind = REC_TRUNCATED;
        if (first) {
            char inner[720];
            memcpy(inner, why, sizeof(inner));
            snprintf(why, sizeof(why), "truncated: last line ends mid-row (%.600s)", inner);
        }
    }
    for (k = 0; kind < 0 && k < 4; k++) {
        if (!isfinite(req[k])) {
            kind = isnan(req[k]) ? REC_MISSING : REC_NON_FINITE;
            if (first && kind == REC_MISSING)
                snprintf(why, sizeof(why), "missing: required column '%s' is empty or nan", REQ[k]);
            else if (first)
                snprintf(why, sizeof(why), "non-finite: required column '%s' is %s", REQ[k], req[k] < 0 ? "-inf" : "inf");
        }
    }
    if (kind < 0 && r->have_t && req[0] < r->tmax) {
        kind = REC_T_DECREASING;
        if (first)
            snprintf(why, sizeof(why), "t decreasing: t=%.17g is below the earlier t=%.17g", req[0], r->tmax);
    }
    if (kind >= 0) {
        if (first)
            snprintf(rec->first_bad_reason, sizeof(rec->first_bad_reason), "%s", why);
        return add_bad(r, line, kind);
    }
    if (add_row(rec, req[0], req + 1) != 0)
        return -1;
    if (!r->have_t || req[0] > r->tmax)
        r->tmax = req[0];
    r->have_t = 1;
    return 0;
}

/* ---- metadata lines: "# key: value" ---- */

typedef struct meta_entry {
    const char *k, *v;
    size_t kn, vn;
} meta_entry;

typedef struct meta_state {
    meta_entry *e;              /* every "key: value" line but comment: */
    long n, cap;
    char *comment;              /* meta["comment"]: free text lines joined by "; " (and comment: keys) */
    size_t cn, ccap;
    int have_comment, any;
} meta_state;

/* do the extents decode to the same text? */
static int same_text(const char *p, size_t pn, const char *q, size_t qn)
{
    name x, y;
    const name *px = &x, *py = &y;
    x.p = p;
    x.n = pn;
    y.p = q;
    y.n = qn;
    return name_cmp(&px, &py) == 0;
}

static int entry_cmp(const void *a, const void *b)
{
    const meta_entry *x = (const meta_entry *)a, *y = (const meta_entry *)b;
    name kx, ky, vx, vy;
    const name *p1 = &kx, *p2 = &ky;
    int c;
    kx.p = x->k, kx.n = x->kn, ky.p = y->k, ky.n = y->kn;
    c = name_cmp(&p1, &p2);
    if (c)
        return c;
    vx.p = x->v, vx.n = x->vn, vy.p = y->v, vy.n = y->vn;
    p1 = &vx;
    p2 = &vy;
    return name_cmp(&p1, &p2);
}

static int comment_put(meta_state *m, const char *p, size_t n)
{
    if (m->cn + n + 1 > m->ccap) {
        size_t cap = 2 * (m->cn + n + 1);
        char *t = (char *)realloc(m->comment, cap);
        if (!t)
            return -1;
        m->comment = t;
        m->ccap = cap;
    }
    memcpy(m->comment + m->cn, p, n);
    m->cn += n;
    return 0;
}

/* One metadata line (read_recording's _parse_meta_line): units.mag is kept; free text and "comment:"
 * lines accumulate; other keys are collected and checked for conflicting values after the header
 * (meta_conflict: order does not matter there). 0, or -1: out of memory. */
static int read_meta(recording *rec, meta_state *m, const char *p, size_t n)
{
    const char *colon, *key, *val;
    size_t kn, vn;
    strip(&p, &n);
    p++;                        /* the '#' */
    n--;
    strip(&p, &n);
    if (!n)
        return 0;
    m->any = 1;
    colon = (const char *)memchr(p, ':', n);
    key = p;
    kn = colon ? (size_t)(colon - p) : 0;
    strip(&key, &kn);
    if (!kn) {                  /* free text: appended to meta["comment"] */
        if (m->have_comment && comment_put(m, "; ", 2) != 0)
            return -1;
        m->have_comment = 1;
        return comment_put(m, p, n);
    }
    val = colon + 1;
    vn = n - (size_t)(colon + 1 - p);
    strip(&val, &vn);
    if (kn == 7 && memcmp(key, "comment", 7) == 0) {   /* notes accumulate, as free text does */
        if (m->have_comment && comment_put(m, "; ", 2) != 0)
            return -1;
        m->have_comment = 1;
        return comment_put(m, val, vn);
    }
    if (m->n == m->cap) {
        long cap = m->cap ? 2 * m->cap : 16;
        meta_entry *t = (meta_entry *)realloc(m->e, (size_t)cap * sizeof(*t));
        if (!t)
            return -1;
        m->e = t;
        m->cap = cap;
    }
    m->e[m->n].k = key;
    m->e[m->n].kn = kn;
    m->e[m->n].v = val;
    m->e[m->n].vn = vn;
    m->n++;
    if (kn == 9 && memcmp(key, "units.mag", 9) == 0) {
        if (!vn)
            snprintf(rec->unit, sizeof(rec->unit), "uT");
        else if (vn < sizeof(rec->unit) && !memchr(val, '\0', vn))
            snprintf(rec->unit, sizeof(rec->unit), "%.*s", (int)vn, val);
        else                    /* kept distinct from any unit name (it cannot be uT) */
            echo(rec->unit, sizeof(rec->unit), val, vn, 12);
    }
    return 0;
}

/* a key with two different values among the "key: value" lines (sorted: they are neighbours) */
static const meta_entry *meta_conflict(meta_state *m)
{
    long i;
    if (m->n < 2)
        return NULL;
    qsort(m->e, (size_t)m->n, sizeof(*m->e), entry_cmp);
    for (i = 1; i < m->n; i++)
        if (same_text(m->e[i - 1].k, m->e[i - 1].kn, m->e[i].k, m->e[i].kn) &&
            !same_text(m->e[i - 1].v, m->e[i - 1].vn, m->e[i].v, m->e[i].vn))
            return &m->e[i];
    return NULL;
}

/* the file cannot be read: rec->error = "PATH: message" (read_recording's RecordingError text) */
static int fail(reader *r, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

static int fail(reader *r, const char *fmt, ...)
{
    char msg[900];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof(msg), fmt, ap);
    va_end(ap);
    recording_free(r->rec);
    snprintf(r->rec->error, sizeof(r->rec->error), "%s: %s", r->path, msg);
    return -1;
}

/* ---- reading the bytes ---- */

#define MAX_HEADER_LINE 65536           /* bytes of a metadata or header line (read_recording's) */
#define MAX_INPUT_BYTES ((size_t)2 << 30) /* an endless input ends with an error, not a full memory */

/* read_recording's _PreambleCheck on the raw bytes as they arrive: every line up to the header row
 * (the first line that is not blank or a '#' comment, by bytes.strip) holds no NUL and at most
 * MAX_HEADER_LINE bytes, so binary or endless input is refused after a bounded read. Line ends
 * \r\n, \r, \n. */
typedef struct preamble {
    size_t pos, scan;           /* start of the line being checked; bytes of it already scanned */
    long lineno;
    int done;
} preamble;

static int byte_space(char c)
{
    return c == ' ' || (c >= '\t' && c <= '\r');
}

static int preamble_feed(reader *r, preamble *pr, const char *buf, size_t len, int eof)
{
    if (pr->lineno == 0 && pr->pos == 0 && len >= 2 &&
        (((unsigned char)buf[0] == 0xff && (unsigned char)buf[1] == 0xfe) ||
         ((unsigned char)buf[0] == 0xfe && (unsigned char)buf[1] == 0xff)))
        return fail(r, "UTF-16 text; a recording is UTF-8 (or ASCII) text");
    while (!pr->done) {
        size_t i = pr->scan, lim = len < pr->pos + MAX_HEADER_LINE + 1 ? len : pr->pos + MAX_HEADER_LINE + 1;
        const char *s, *e;
        while (i < lim && buf[i] != '\n' && buf[i] != '\r' && buf[i] != '\0')
            i++;
        pr->scan = i;
        if (i < lim && buf[i] == '\0')
            return fail(r, "line %ld holds NUL bytes before the header row: binary data, not a recording "
                           "(a text CSV)", pr->lineno + 1);
        if (i - pr->pos > MAX_HEADER_LINE)
            return fail(r, "line %ld is longer than %d bytes before the header row ends: not a recording "
                           "(a transposed table or binary data?)", pr->lineno + 1, MAX_HEADER_LINE);
        if (i == len && !eof)
            return 0;           /* the line goes on in the next block */
        if (i < len && buf[i] == '\r' && i + 1 == len && !eof)
            return 0;           /* may be the first half of \r\n */
        pr->lineno++;
        s = buf + pr->pos;
        e = buf + i;
        while (s < e && byte_space(*s))
            s++;
        while (e > s && byte_space(e[-1]))
            e--;
        if (e - s >= 3 && memcmp(s, "\xef\xbb\xbf", 3) == 0)
            for (s += 3; s < e && byte_space(*s); s++)
                ;
        if (s < e && *s != '#')
            pr->done = 1;
        if (i == len) {
            pr->done = 1;       /* the end of the input */
            break;
        }
        pr->pos = pr->scan = i + (buf[i] == '\r' && i + 1 < len && buf[i + 1] == '\n' ? 2 : 1);
    }
    return 0;
}

/* the whole file into a buffer with room for a final NUL */
static int read_file(reader *r, char **text, size_t *len)
{
    FILE *f;
    char *buf = NULL;
    size_t n = 0, cap = 0, got;
    preamble pr;
    int err, gz = -1;
    memset(&pr, 0, sizeof(pr));
    errno = 0;
    f = fopen(r->path, "rb");
    if (!f)
        return fail(r, "cannot open: %s", strerror(errno));
    for (;;) {
        if (cap - n < 65536 + 1) {
            size_t c2 = cap ? 2 * cap : 65536 * 2;
            char *t = c2 > cap ? (char *)realloc(buf, c2) : NULL;
            if (!t) {
                free(buf);
                fclose(f);
                return fail(r, "out of memory reading the file");
            }
            buf = t;
            cap = c2;
        }
        got = fread(buf + n, 1, 65536, f);
        n += got;
        if (gz < 0 && n >= 2)
            gz = (unsigned char)buf[0] == 0x1f && (unsigned char)buf[1] == 0x8b;
        if (gz == 1 || n > MAX_INPUT_BYTES || (got == 65536 && preamble_feed(r, &pr, buf, n, 0) != 0))
            break;
        if (got < 65536)
            break;
    }
    err = ferror(f) ? errno : 0;
    fclose(f);
    if (err) {
        free(buf);
#ifdef EISDIR
        if (err == EISDIR)
            return fail(r, "is a directory, not a recording file");
#endif
        return fail(r, "cannot read: %s", strerror(err));
    }
    if (*r->rec->error) {
        free(buf);
        return -1;
    }
    if (gz == 1) {
        free(buf);
        return fail(r, "gzip-compressed: mkc_replay reads plain .csv (gunzip it first)");
    }
    if (n > MAX_INPUT_BYTES) {
        free(buf);
        return fail(r, "more than %lu MiB of text; too large for a recording (or an endless input)",
                    (unsigned long)(MAX_INPUT_BYTES >> 20));
    }
    if (preamble_feed(r, &pr, buf, n, 1) != 0) {
        free(buf);
        return -1;
    }
    *text = buf;
    *len = n;
    return 0;
}

int recording_read(recording *rec, const char *path, int keep_bad_rows)
{
    reader r;
    meta_state m;
    char *text = NULL, *end, *p, *header = NULL, *hend = NULL, *lastline = NULL;
    char e1[ECHO_MAX * 4 + 8], e2[ECHO_MAX * 4 + 8];
    size_t len = 0;
    long lineno = 0, header_line = 0, j, k;
    int ends_nl, rc = -1;
    memset(rec, 0, sizeof(*rec));
    memset(&r, 0, sizeof(r));
    memset(&m, 0, sizeof(m));
    snprintf(rec->unit, sizeof(rec->unit), "uT");
    r.rec = rec;
    r.path = path;
    r.keep_bad = keep_bad_rows;
    if (read_file(&r, &text, &len) != 0)
        return -1;
    text[len] = '\0';
    /* BOM; CR LF and lone CR become LF */
    {
        size_t i = 0, o = 0;
        if (len >= 3 && (unsigned char)text[0] == 0xef && (unsigned char)text[1] == 0xbb &&
            (unsigned char)text[2] == 0xbf)
            i = 3;
        for (; i < len; i++) {
            if (text[i] == '\r') {
                text[o++] = '\n';
                if (i + 1 < len && text[i + 1] == '\n')
                    i++;
            } else {
                text[o++] = text[i];
            }
        }
        text[o] = '\0';
        len = o;
    }
    end = text + len;
    /* metadata lines, then the header; each holds no NUL and at most MAX_HEADER_LINE characters */
    for (p = text; p < end;) {
        char *nl = (char *)memchr(p, '\n', (size_t)(end - p)), *le = nl ? nl : end;
        const char *s;
        size_t nchar = 0, kc;
        lineno++;
        if (memchr(p, '\0', (size_t)(le - p))) {
            free(text);
            free(m.e);
            free(m.comment);
            return fail(&r, "line %ld holds NUL bytes before the header row: binary data, not a recording "
                            "(a text CSV)", lineno);
        }
        for (s = p; s < le && nchar <= MAX_HEADER_LINE; s += kc, nchar++)
            next_char(s, le, &kc);
        if (nchar > MAX_HEADER_LINE) {
            free(text);
            free(m.e);
            free(m.comment);
            return fail(&r, "line %ld is longer than %d characters before the header row ends: not a recording "
                            "(a transposed table or binary data?)", lineno, MAX_HEADER_LINE);
        }
        s = skip_space(p, le);
        if (s < le && *s == '#') {
            int st = read_meta(rec, &m, p, (size_t)(le - p));
            if (st < 0) {
                free(text);
                free(m.e);
                free(m.comment);
                return fail(&r, "out of memory reading the file");
            }
        } else if (s < le) {
            header = p;
            hend = le;
            header_line = lineno;
            p = nl ? nl + 1 : end;
            break;
        }
        p = nl ? nl + 1 : end;
    }
    {
        const meta_entry *c = meta_conflict(&m);
        if (c)
            echo(e1, sizeof(e1), c->k, c->kn, 40);
        free(m.e);
        free(m.comment);
        if (c) {
            free(text);
            return fail(&r, "metadata '%s' is given twice with different values", e1);
        }
    }
    if (!header) {
        free(text);
        return fail(&r, "the file %s; a recording needs a header row with at least t,mx,my,mz and data rows",
                    m.any ? "holds only metadata lines (no header row)" : "is empty");
    }
    /* the header: names, none empty, none repeated, the four required ones present */
    {
        const char *c;
        long ncol = 1;
        for (c = header; (c = (const char *)memchr(c, ',', (size_t)(hend - c))) != NULL; c++)
            ncol++;
        r.names = (name *)malloc((size_t)ncol * sizeof(name));
        if (!r.names)
            goto oom;
        r.ncol = ncol;
        echo(e2, sizeof(e2), header, (size_t)(hend - header), ECHO_MAX);
        for (j = 0, c = header; j < ncol; j++) {
            const char *ce = (const char *)memchr(c, ',', (size_t)(hend - c));
            if (!ce)
                ce = hend;
            r.names[j].p = c;
            r.names[j].n = (size_t)(ce - c);
            strip(&r.names[j].p, &r.names[j].n);
            c = ce + 1;
        }
        for (j = 0; j < ncol; j++) {
            if (!r.names[j].n) {
                free(r.names);
                free(text);
                return fail(&r, "line %ld: empty column name in header '%s'", header_line, e2);
            }
        }
        {
            /* sorted: repeats are neighbours (n log n, not a pairwise check) */
            const name **sorted = (const name **)malloc((size_t)ncol * sizeof(*sorted));
            char list[ECHO_MAX * 4 + 64];
            size_t o = 0;
            int ndup = 0;
            if (!sorted)
                goto oom;
            for (j = 0; j < ncol; j++)
                sorted[j] = &r.names[j];
            qsort(sorted, (size_t)ncol, sizeof(*sorted), name_cmp);
            for (j = 1; j < ncol; j++) {
                if (name_cmp(&sorted[j - 1], &sorted[j]) == 0 && (j == 1 || name_cmp(&sorted[j - 2], &sorted[j]) != 0)) {
                    if (ndup < 4) {
                        echo(e1, sizeof(e1), sorted[j]->p, sorted[j]->n, ECHO_MAX / 4);
                        o += (size_t)snprintf(list + o, sizeof(list) - o, "%s'%s'", ndup ? ", " : "", e1);
                    } else if (ndup == 4) {
                        o += (size_t)snprintf(list + o, sizeof(list) - o, ", ...");
                    }
                    ndup++;
                }
            }
            free((void *)sorted);
            if (ndup) {
                free(r.names);
                free(text);
                return fail(&r, "line %ld: duplicate column name(s) [%s] in header", header_line, list);
            }
        }
        {
            char missing[64] = "";
            for (k = 0; k < 4; k++) {
                r.col[k] = -1;
                for (j = 0; j < ncol && r.col[k] < 0; j++)
                    if (r.names[j].n == strlen(REQ[k]) && memcmp(r.names[j].p, REQ[k], r.names[j].n) == 0)
                        r.col[k] = j;
                if (r.col[k] < 0)
                    snprintf(missing + strlen(missing), sizeof(missing) - strlen(missing), "%s%s", *missing ? ", " : "",
                             REQ[k]);
            }
            if (*missing) {
                free(r.names);
                free(text);
                return fail(&r, "line %ld: missing required column(s) %s; the header is '%s' but a recording needs "
                                "t, mx, my, mz", header_line, missing, e2);
            }
        }
    }
    /* the body: when the file does not end with a line end, its last non-blank line may be cut short */
    ends_nl = len > 0 && text[len - 1] == '\n';
    if (!ends_nl) {
        char *e = end;
        while (e > p) {
            char *s = e;
            while (s > p && s[-1] != '\n')
                s--;
            if (skip_space(s, e) < e) {
                lastline = s;
                break;
            }
            if (s == p)
                break;
            e = s - 1;
        }
    }
    for (lineno = header_line + 1; p < end; lineno++) {
        char *nl = (char *)memchr(p, '\n', (size_t)(end - p)), *le = nl ? nl : end;
        if (read_row(&r, p, (size_t)(le - p), lineno, p == lastline) != 0)
            goto oom;
        p = nl ? nl + 1 : end;
    }
    rc = 0;
    free(r.names);
    free(r.sc.s);
    free(text);
    return rc;
oom:
    free(r.names);
    free(r.sc.s);
    free(text);
    return fail(&r, "out of memory reading the file");
}

void recording_free(recording *rec)
{
    free(rec->t);
    free(rec->mag);
    free(rec->bad_line);
    free(rec->bad_kind);
    rec->t = rec->mag = NULL;
    rec->bad_line = NULL;
    rec->bad_kind = NULL;
    rec->n = rec->cap = rec->nbad = rec->badcap = 0;
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

long recording_gaps(const recording *rec)
{
    long i, np = 0, gaps = 0;
    double *pos, med;
    if (rec->n < 2)
        return 0;
    pos = (double *)malloc((size_t)(rec->n - 1) * sizeof(double));
    if (!pos)
        return 0;
    for (i = 0; i + 1 < rec->n; i++) {
        double dt = rec->t[i + 1] - rec->t[i];
        if (dt > 0.0)
            pos[np++] = dt;
    }
    if (np < 2) {
        free(pos);
        return 0;
    }
    qsort(pos, (size_t)np, sizeof(double), cmp_double);
    med = np % 2 ? pos[np / 2] : (pos[np / 2 - 1] + pos[np / 2]) / 2.0;
    for (i = 0; i + 1 < rec->n; i++)
        if (rec->t[i + 1] - rec->t[i] > 2.5 * med)
            gaps++;
    free(pos);
    return gaps;
}
