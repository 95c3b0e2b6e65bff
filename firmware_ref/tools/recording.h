/* recording.h: reader of the recording CSV (docs/spec/recording.md) for the host tools (not the library).
 *
 * The rules of mkc_stream/io/recording.py read_recording: optional "# key: value" metadata lines,
 * one header row with t, mx, my, mz (any other columns allowed; an empty or repeated column name
 * makes the file unreadable), one row per sample. A row is bad (counted, with its 1-based line
 * number and kind) when a required cell is missing, not a number or not finite, when any cell is
 * not a number, when it has the wrong number of cells, when it is a comment after the header, when
 * it is the cut-off last line of the file, or when its t is below the largest t accepted before it.
 * Blank lines are skipped. gzip input is not supported (gunzip first).
 *
 * The text is read as Python reads it (bytes.decode("utf-8", "replace")): NUL bytes are ordinary
 * characters, whitespace is Python's str.isspace, a number is what Python's float() accepts (with
 * `_` separators and Unicode decimal digits), invalid UTF-8 compares as U+FFFD. As there, the lines
 * up to the header row hold no NUL and at most 64 KiB, a metadata key has one value, UTF-16 and
 * input over 2 GiB are refused. Time and memory are linear in the file size.
 */
#ifndef MKC_RECORDING_H
#define MKC_RECORDING_H

#include <stddef.h>

/* kinds of bad rows: the part of read_recording's reason before ": " */
enum rec_kind {
    REC_NON_NUMERIC,
    REC_MISSING,
    REC_NON_FINITE,
    REC_CELL_COUNT,
    REC_TRUNCATED,
    REC_T_DECREASING,
    REC_COMMENT,
    REC_NKINDS
};
extern const char *const rec_kind_names[REC_NKINDS];

typedef struct recording {
    double *t;                  /* n */
    double *mag;                /* n x 3 */
    long n, cap;
    long nbad;                  /* bad rows */
    long first_bad_line;        /* line and reason of the first bad row (nbad > 0) */
    char first_bad_reason[720]; /* echoes of the file are capped and escaped */
    long *bad_line;             /* every bad row's line and kind: only with keep_bad_rows */
    unsigned char *bad_kind;
    long badcap;
    char unit[64];              /* units.mag, default "uT" */
    char error[1024];           /* why the file cannot be read at all */
} recording;

/* 0 on success (bad rows are not failures), -1 with rec->error set (and nothing to free).
 * keep_bad_rows: also list every bad row (else only the count and the first one). */
int recording_read(recording *rec, const char *path, int keep_bad_rows);
void recording_free(recording *rec);
/* the code point at p (n > 0 bytes) as Python's UTF-8 decoder with errors="replace" reads it: 0xFFFD
 * for an invalid sequence; *len its bytes (an invalid sequence never swallows an ASCII byte) */
unsigned long recording_u8char(const char *p, size_t n, size_t *len);
/* time steps larger than 2.5 x the median positive step (Recording.counts()["gaps"]) */
long recording_gaps(const recording *rec);

#endif
