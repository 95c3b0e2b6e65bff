/* recording.c: the recording CSV reader of the host tools (rules in recording.h). */
#include "recording.h"

#include <ctype.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int add_bad(recording *rec, long line, const char *reason)
{
    if (rec->nbad == rec->badcap) {
        long cap = rec->badcap ? 2 * rec->badcap : 64;
        rec_bad_row *b = (rec_bad_row *)realloc(rec->bad, (size_t)cap * sizeof(*b));
        if (!b)
            return -1;
        rec->bad = b;
        rec->badcap = cap;
    }
    rec->bad[rec->nbad].line = line;
    snprintf(rec->bad[rec->nbad].reason, sizeof(rec->bad[rec->nbad].reason), "%s", reason);
    rec->nbad++;
    return 0;
}

static int add_row(recording *rec, double t, const double *m)
{
    if (rec->n == rec->cap) {
        long cap = rec->cap ? 2 * rec->cap : 4096;
        double *tt = (double *)realloc(rec->t, (size_t)cap * sizeof(double));
        double *mm;
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

/* strip in place (Python str.strip: whitespace) */
static char *strip(char *s)
{
    char *e;
    while (*s && isspace((unsigned char)*s))
        s++;
    e = s + strlen(s);
    while (e > s && isspace((unsigned char)e[-1]))
        *--e = '\0';
    return s;
}

static int ieq(const char *a, const char *b)
{
    while (*a && *b) {
        if (tolower((unsigned char)*a) != tolower((unsigned char)*b))
            return 0;
        a++;
        b++;
    }
    return *a == *b;
}

/* digits with single underscores between them (Python's digitpart); returns chars consumed */
static size_t digitpart(const char *s)
{
    size_t k = 0;
    if (!isdigit((unsigned char)s[0]))
        return 0;
    while (isdigit((unsigned char)s[k]) || (s[k] == '_' && isdigit((unsigned char)s[k + 1]) && k > 0))
        k++;
    return k;
}

/* Python float(cell): 0 and *v on success; NaN for an empty cell; -1 when not a number. */
static int cell_value(char *cell, double *v)
{
    char *c = strip(cell), buf[512];
    const char *p = c, *w;
    size_t k, j;
    if (!*c) {
        *v = NAN;
        return 0;
    }
    w = (*p == '+' || *p == '-') ? p + 1 : p;
    if (ieq(w, "inf") || ieq(w, "infinity")) {
        *v = *p == '-' ? -HUGE_VAL : HUGE_VAL;
        return 0;
    }
    if (ieq(w, "nan")) {
        *v = NAN;
        return 0;
    }
    p = w;
    k = digitpart(p);
    p += k;
    if (*p == '.') {
        size_t f = digitpart(p + 1);
        if (!k && !f)
            return -1;
        p += 1 + f;
    } else if (!k) {
        return -1;
    }
    if (*p == 'e' || *p == 'E') {
        const char *q = p + 1;
        if (*q == '+' || *q == '-')
            q++;
        k = digitpart(q);
        if (!k)
            return -1;
        p = q + k;
    }
    if (*p)
        return -1;
    if (strlen(c) >= sizeof(buf))
        return -1;
    for (k = 0, j = 0; c[k]; k++)
        if (c[k] != '_')
            buf[j++] = c[k];
    buf[j] = '\0';
    *v = strtod(buf, NULL);
    return 0;
}

static int parse_meta(recording *rec, char *line)
{
    char *content = strip(line) + 1, *colon;
    content = strip(content);
    colon = strchr(content, ':');
    if (colon) {
        char *key, *value;
        *colon = '\0';
        key = strip(content);
        value = strip(colon + 1);
        if (*key && strcmp(key, "units.mag") == 0)
            snprintf(rec->unit, sizeof(rec->unit), "%s", *value ? value : "uT");
    }
    return 0;
}

int recording_read(recording *rec, const char *path)
{
    FILE *f = fopen(path, "rb");
    char *text = NULL, *line, *next, *header = NULL;
    size_t len = 0, cap = 0, got;
    long lineno = 0, header_line = 0, ncol = 0, col[4] = {-1, -1, -1, -1}, k;
    char *names[256];
    static const char *req[4] = {"t", "mx", "my", "mz"};
    double tmax = -HUGE_VAL;
    int have_t = 0, ends_nl;
    long last_nonblank = -1, nlines = 0;
    memset(rec, 0, sizeof(*rec));
    snprintf(rec->unit, sizeof(rec->unit), "uT");
    if (!f) {
        snprintf(rec->error, sizeof(rec->error), "cannot open %s", path);
        return -1;
    }
    for (;;) {
        if (len + 65536 + 1 > cap) {
            char *t2;
            cap = cap ? 2 * cap : 1 << 20;
            t2 = (char *)realloc(text, cap);
            if (!t2) {
                fclose(f);
                free(text);
                snprintf(rec->error, sizeof(rec->error), "out of memory reading %s", path);
                return -1;
            }
            text = t2;
        }
        got = fread(text + len, 1, 65536, f);
        len += got;
        if (got < 65536)
            break;
    }
    fclose(f);
    if (!text) {
        snprintf(rec->error, sizeof(rec->error), "%s: the file is empty", path);
        return -1;
    }
    text[len] = '\0';
    if (len >= 2 && (unsigned char)text[0] == 0x1f && (unsigned char)text[1] == 0x8b) {
        free(text);
        snprintf(rec->error, sizeof(rec->error), "%s is gzip-compressed: mkc_replay reads plain .csv (gunzip it first)",
                 path);
        return -1;
    }
    /* BOM; CR LF and lone CR become LF */
    {
        size_t i = 0, o = 0;
        if (len >= 3 && (unsigned char)text[0] == 0xef && (unsigned char)text[1] == 0xbb && (unsigned char)text[2] == 0xbf)
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
    /* metadata lines, then the header */
    line = text;
    while (line < text + len) {
        char *s;
        next = strchr(line, '\n');
        if (next)
            *next = '\0';
        lineno++;
        s = strip(line);
        if (!*s) {
            if (!next)
                break;
            line = next + 1;
            continue;
        }
        if (*s == '#') {
            parse_meta(rec, line);
            if (!next)
                break;
            line = next + 1;
            continue;
        }
        header = line;
        header_line = lineno;
        line = next ? next + 1 : text + len;
        break;
    }
    if (!header) {
        free(text);
        snprintf(rec->error, sizeof(rec->error), "%s: the file has no header row; a recording needs a header row "
                                                 "with at least t,mx,my,mz and data rows", path);
        return -1;
    }
    {
        char *p = header, *c;
        for (;;) {
            c = strchr(p, ',');
            if (c)
                *c = '\0';
            if (ncol == 256) {
                free(text);
                snprintf(rec->error, sizeof(rec->error), "%s: line %ld: more than 256 columns", path, header_line);
                return -1;
            }
            names[ncol] = strip(p);
            if (!*names[ncol]) {
                free(text);
                snprintf(rec->error, sizeof(rec->error), "%s: line %ld: empty column name in header", path, header_line);
                return -1;
            }
            for (k = 0; k < ncol; k++) {
                if (strcmp(names[k], names[ncol]) == 0) {
                    free(text);
                    snprintf(rec->error, sizeof(rec->error), "%s: line %ld: duplicate column name '%s' in header", path,
                             header_line, names[ncol]);
                    return -1;
                }
            }
            for (k = 0; k < 4; k++)
                if (strcmp(names[ncol], req[k]) == 0)
                    col[k] = ncol;
            ncol++;
            if (!c)
                break;
            p = c + 1;
        }
        for (k = 0; k < 4; k++) {
            if (col[k] < 0) {
                free(text);
                snprintf(rec->error, sizeof(rec->error), "%s: line %ld: missing required column %s; a recording needs "
                                                         "t, mx, my, mz", path, header_line, req[k]);
                return -1;
            }
        }
    }
    /* body: the last non-blank line may be cut short when the file does not end with a newline */
    ends_nl = len > 0 && text[len - 1] == '\n';
    {
        char *p = line;
        long i = 0;
        while (p < text + len) {
            char *e = strchr(p, '\n');
            char *s;
            size_t L = e ? (size_t)(e - p) : strlen(p);
            int blank = 1;
            for (s = p; s < p + L; s++)
                if (!isspace((unsigned char)*s))
                    blank = 0;
            if (!blank)
                last_nonblank = i;
            i++;
            if (!e)
                break;
            p = e + 1;
        }
        nlines = i;
    }
    for (k = 0; k < nlines && line < text + len + 1; k++) {
        char *e = strchr(line, '\n'), *cells[256], *p, *s, reason[160];
        long n = 0, lno = header_line + 1 + k;
        double vals[256];
        int bad = 0, is_last = (k == last_nonblank) && !ends_nl;
        if (e)
            *e = '\0';
        s = line;
        while (*s && isspace((unsigned char)*s))
            s++;
        if (!*s) {
            line = e ? e + 1 : text + len + 1;
            continue;
        }
        reason[0] = '\0';
        if (*s == '#') {
            snprintf(reason, sizeof(reason), "unexpected comment: comment line after the header");
            bad = 1;
        } else {
            p = line;
            for (;;) {
                char *c = strchr(p, ',');
                if (c)
                    *c = '\0';
                if (n < 256)
                    cells[n] = p;
                n++;
                if (!c)
                    break;
                p = c + 1;
            }
            if (n != ncol) {
                snprintf(reason, sizeof(reason), "cell count: expected %ld cells, got %ld", ncol, n);
                bad = 1;
            } else {
                long j;
                for (j = 0; j < ncol; j++) {
                    if (cell_value(cells[j], &vals[j]) != 0) {
                        snprintf(reason, sizeof(reason), "non-numeric: column '%.100s'", names[j]);
                        bad = 1;
                        break;
                    }
                }
            }
        }
        if (bad && is_last) {
            char inner[160];
            memcpy(inner, reason, sizeof(inner));
            snprintf(reason, sizeof(reason), "truncated: last line ends mid-row (%.100s)", inner);
        }
        if (!bad) {
            long j;
            for (j = 0; j < 4; j++) {
                double v = vals[col[j]];
                if (!isfinite(v)) {
                    snprintf(reason, sizeof(reason), isnan(v) ? "missing: required column '%s' is empty or nan"
                                                             : "non-finite: required column '%s'", req[j]);
                    bad = 1;
                    break;
                }
            }
        }
        if (!bad && have_t && vals[col[0]] < tmax) {
            snprintf(reason, sizeof(reason), "t decreasing: t=%.17g is below the earlier t=%.17g", vals[col[0]], tmax);
            bad = 1;
        }
        if (bad) {
            if (add_bad(rec, lno, reason) != 0)
                goto oom;
        } else {
            double m[3];
            m[0] = vals[col[1]];
            m[1] = vals[col[2]];
            m[2] = vals[col[3]];
            if (add_row(rec, vals[col[0]], m) != 0)
                goto oom;
            if (!have_t || vals[col[0]] > tmax)
                tmax = vals[col[0]];
            have_t = 1;
        }
        line = e ? e + 1 : text + len + 1;
    }
    free(text);
    return 0;
oom:
    free(text);
    snprintf(rec->error, sizeof(rec->error), "out of memory reading %s", path);
    return -1;
}

void recording_free(recording *rec)
{
    free(rec->t);
    free(rec->mag);
    free(rec->bad);
    memset(rec, 0, sizeof(*rec));
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
