/* recording.h: reader of the recording CSV (spec/recording.md) for the host tools (not the library).
 *
 * The rules of mkc_stream/io/recording.py read_recording: optional "# key: value" metadata lines,
 * one header row with t, mx, my, mz (any other columns allowed), one row per sample. A row is bad
 * (counted, with its 1-based line number and reason) when a required cell is missing, not a number
 * or not finite, when any cell is not a number, when it has the wrong number of cells, when it is a
 * comment after the header, when it is the cut-off last line of the file, or when its t is below the
 * largest t accepted before it. Blank lines are skipped. gzip input is not supported (gunzip first).
 */
#ifndef MKC_RECORDING_H
#define MKC_RECORDING_H

#include <stddef.h>

typedef struct rec_bad_row {
    long line;
    char reason[160];
} rec_bad_row;

typedef struct recording {
    double *t;          /* n */
    double *mag;        /* n x 3 */
    long n, cap;
    rec_bad_row *bad;   /* nbad */
    long nbad, badcap;
    char unit[64];      /* units.mag, default "uT" */
    char error[512];    /* why the file cannot be read at all */
} recording;

/* 0 on success (bad rows are not failures), -1 with rec->error set. */
int recording_read(recording *rec, const char *path);
void recording_free(recording *rec);
/* time steps larger than 2.5 x the median positive step (Recording.counts()["gaps"]) */
long recording_gaps(const recording *rec);

#endif
