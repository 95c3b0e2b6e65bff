/* introspect.c: read and write access to a state's fields as doubles, for tests, tools and the ctypes
 * bridge (mkc_stream/cport). Not needed by firmware; no I/O. */
#include "mkc_internal.h"
#include "mkc_introspect.h"

/* Copy n bytes (the library uses no libc beyond libm). */
static void copy_bytes(void *to, const void *from, size_t n)
{
    unsigned char *t = (unsigned char *)to;
    const unsigned char *f = (const unsigned char *)from;
    size_t i;
    for (i = 0; i < n; i++)
        t[i] = f[i];
}

static int put(double *out, int cap, int k, double v)
{
    if (k < cap)
        out[k] = v;
    return k + 1;
}

/* MKC_F_SLOT_AGE as written: stamps 0 .. count-1 in the order of the ages in[0..count-1] (ties: the
 * lower slot first, as the reference's choice). */
static void set_stamps(mkc_mag_t *g, const double *in, int count)
{
    int s, t;
    for (s = 0; s < count; s++) {
        int rank = 0;
        for (t = 0; t < count; t++)
            rank += in[t] < in[s] || (in[t] == in[s] && t < s);
        g->slot_stamp[s] = (uint16_t)rank;
    }
    g->next_stamp = (uint16_t)count;
}

int mkc_get(const void *state, int kind, int which, double *out, int cap)
{
    const mkc_core_t *c = (const mkc_core_t *)state;
    const mkc_stream_t *st = kind == 0 ? (const mkc_stream_t *)state : NULL;
    const mkc_mag_t *g = kind == 1 ? (const mkc_mag_t *)state : NULL;
    int64_t cnt[MKC_COUNTERS];   /* the counters as the Python state's cnt array (mkc_internal.h checks the layout) */
    int n, m, count, k = 0, s, i, j;
    if (!state || (kind != 0 && kind != 1))
        return -1;
    n = c->cfg.n;
    m = c->cfg.m;
    count = (int)c->counters.count;
    switch (which) {
    case MKC_F_THETA:
        for (j = 0; j < n; j++)
            k = put(out, cap, k, (double)c->theta[j]);
        break;
    case MKC_F_SIGMA:
        for (i = 0; i < m; i++)
            k = put(out, cap, k, (double)c->sigma[i]);
        break;
    case MKC_F_D:
        for (i = 0; i < m; i++)
            k = put(out, cap, k, (double)c->d[i]);
        break;
    case MKC_F_A:
        for (i = 0; i < m; i++)
            k = put(out, cap, k, (double)c->a[i]);
        break;
    case MKC_F_HES:
        for (i = 0; i < m; i++)
            for (j = 0; j < 3; j++)
                k = put(out, cap, k, (double)c->Hes[i][j]);
        break;
    case MKC_F_C:
        for (s = 0; s < count; s++)
            for (i = 0; i < m; i++)
                k = put(out, cap, k, (double)c->C[s][i]);
        break;
    case MKC_F_COND:
        k = put(out, cap, k, (double)c->fit.cond);
        break;
    case MKC_F_LAST_F:
        k = put(out, cap, k, (double)c->fit.last_objective);
        break;
    case MKC_F_CNT:
        copy_bytes(cnt, &c->counters, sizeof cnt);
        for (j = 0; j < MKC_COUNTERS; j++)
            k = put(out, cap, k, (double)cnt[j]);
        break;
    case MKC_F_NORMAL_A:
        for (i = 0; i < n; i++)
            for (j = 0; j < n; j++)
                k = put(out, cap, k, (double)(j <= i ? c->A[i][j] : c->A[j][i]));
        break;
    case MKC_F_NORMAL_B:
        for (j = 0; j < n; j++)
            k = put(out, cap, k, (double)c->b[j]);
        break;
    case MKC_F_RAW:
        if (!g)
            return -1;
        for (s = 0; s < count; s++)
            for (j = 0; j < 3; j++)
                k = put(out, cap, k, (double)g->raw[s][j]);
        break;
    case MKC_F_C0S0:
        if (!g)
            return -1;
        for (j = 0; j < 3; j++)
            k = put(out, cap, k, (double)g->c0[j]);
        k = put(out, cap, k, (double)g->s0);
        break;
    case MKC_F_X:
        for (s = 0; s < count; s++) {
            for (i = 0; i < m; i++) {
                mkc_real buf[MKC_N];
                const mkc_real *x = mkc__row(c, s, i, buf);
                for (j = 0; j < n; j++)
                    k = put(out, cap, k, (double)x[j]);
            }
        }
        break;
    case MKC_F_Y:
        for (s = 0; s < count; s++)
            for (i = 0; i < m; i++)
                k = put(out, cap, k, st ? (double)st->Y[s][i] : 1.0);
        break;
    case MKC_F_L:
        for (i = 0; i < n; i++)
            for (j = 0; j < n; j++)
                k = put(out, cap, k, (double)c->L[i][j]);
        break;
    case MKC_F_DEQ:
        for (j = 0; j < n; j++)
            k = put(out, cap, k, (double)c->D[j]);
        break;
    case MKC_F_XS:
        for (j = 0; j < n; j++)
            k = put(out, cap, k, (double)c->xs[j]);
        break;
    case MKC_F_TPREV:
        for (j = 0; j < n; j++)
            k = put(out, cap, k, (double)c->tprev[j]);
        break;
    case MKC_F_SLOT_AGE:
        if (!g)
            return -1;
        for (s = 0; s < count; s++)
            k = put(out, cap, k, (double)g->slot_stamp[s]);
        break;
    case MKC_F_SLOT_CELL:
        if (!g)
            return -1;
        for (s = 0; s < count; s++)
            k = put(out, cap, k, (double)g->slot_cell[s]);
        break;
    case MKC_F_CELL_COUNT:
        if (!g)
            return -1;
        for (j = 0; j < MKC_CELLS; j++)
            k = put(out, cap, k, (double)g->cell_count[j]);
        break;
    case MKC_F_MAG_FLAGS:
        if (!g)
            return -1;
        k = put(out, cap, k, (double)g->provisional);
        k = put(out, cap, k, (double)g->failed);
        k = put(out, cap, k, (double)g->misfit);
        k = put(out, cap, k, (double)g->has_confirmed);
        for (j = 0; j < 3; j++)
            k = put(out, cap, k, (double)g->confirmed_b[j]);
        k = put(out, cap, k, (double)g->confirmed_F);
        k = put(out, cap, k, (double)g->first_accepted_at);
        break;
    default:
        return -1;
    }
    return k;
}

int mkc_set(void *state, int kind, int which, const double *in, int n)
{
    mkc_core_t *c = (mkc_core_t *)state;
    mkc_stream_t *st = kind == 0 ? (mkc_stream_t *)state : NULL;
    mkc_mag_t *g = kind == 1 ? (mkc_mag_t *)state : NULL;
    int64_t cnt[MKC_COUNTERS];
    int np, m, count, k = 0, s, i, j, need;
    if (!state || (kind != 0 && kind != 1) || !in)
        return MKC_BAD_INPUT;
    np = c->cfg.n;
    m = c->cfg.m;
    count = (int)c->counters.count;
    switch (which) {
    case MKC_F_THETA: case MKC_F_NORMAL_B: case MKC_F_DEQ: case MKC_F_XS: case MKC_F_TPREV: need = np; break;
    case MKC_F_SIGMA: case MKC_F_D: case MKC_F_A: need = m; break;
    case MKC_F_HES: need = 3 * m; break;
    case MKC_F_C: need = count * m; break;
    case MKC_F_COND: case MKC_F_LAST_F: need = 1; break;
    case MKC_F_CNT: need = MKC_COUNTERS; break;
    case MKC_F_NORMAL_A: case MKC_F_L: need = np * np; break;
    case MKC_F_RAW: need = 3 * count; break;
    case MKC_F_C0S0: need = 4; break;
    case MKC_F_X: need = st ? count * m * np : -1; break;
    case MKC_F_Y: need = st ? count * m : -1; break;
    case MKC_F_SLOT_AGE: case MKC_F_SLOT_CELL: need = count; break;
    case MKC_F_CELL_COUNT: need = MKC_CELLS; break;
    case MKC_F_MAG_FLAGS: need = 9; break;
    default: need = -1;
    }
    if (need < 0 || n != need || (!g && which >= MKC_F_SLOT_AGE) || (!g && (which == MKC_F_RAW || which == MKC_F_C0S0)))
        return MKC_BAD_INPUT;
    if (which == MKC_F_CNT) {
        if (in[MKC_C_COUNT] < 0 || in[MKC_C_COUNT] > c->cfg.window)
            return MKC_BAD_INPUT;
        for (j = 0; j < MKC_COUNTERS; j++)
            cnt[j] = (int64_t)in[j];
        copy_bytes(&c->counters, cnt, sizeof cnt);
        return MKC_OK;
    }
    for (k = 0; k < n; k++)
        if (!isfinite(in[k]) && which != MKC_F_COND)
            return MKC_BAD_INPUT;
    k = 0;
    switch (which) {
    case MKC_F_THETA: for (j = 0; j < np; j++) c->theta[j] = (mkc_real)in[k++]; break;
    case MKC_F_NORMAL_B: for (j = 0; j < np; j++) c->b[j] = (mkc_acc)in[k++]; break;
    case MKC_F_DEQ: for (j = 0; j < np; j++) c->D[j] = (mkc_acc)in[k++]; break;
    case MKC_F_XS: for (j = 0; j < np; j++) c->xs[j] = (mkc_acc)in[k++]; break;
    case MKC_F_TPREV: for (j = 0; j < np; j++) c->tprev[j] = (mkc_real)in[k++]; break;
    case MKC_F_SIGMA: for (i = 0; i < m; i++) c->sigma[i] = (mkc_real)in[k++]; break;
    case MKC_F_D: for (i = 0; i < m; i++) c->d[i] = (mkc_real)in[k++]; break;
    case MKC_F_A: for (i = 0; i < m; i++) c->a[i] = (mkc_real)in[k++]; break;
    case MKC_F_HES: for (i = 0; i < m; i++) for (j = 0; j < 3; j++) c->Hes[i][j] = (mkc_ereal)in[k++]; break;
    case MKC_F_C: for (s = 0; s < count; s++) for (i = 0; i < m; i++) c->C[s][i] = (mkc_real)in[k++]; break;
    case MKC_F_COND: c->fit.cond = (mkc_real)in[0]; break;
    case MKC_F_LAST_F: c->fit.last_objective = (mkc_real)in[0]; break;
    case MKC_F_NORMAL_A: for (i = 0; i < np; i++) for (j = 0; j < np; j++) c->A[i][j] = (mkc_acc)in[k++]; break;
    case MKC_F_L: for (i = 0; i < np; i++) for (j = 0; j < np; j++) c->L[i][j] = (mkc_acc)in[k++]; break;
    case MKC_F_RAW: for (s = 0; s < count; s++) for (j = 0; j < 3; j++) g->raw[s][j] = (mkc_real)in[k++]; break;
    case MKC_F_C0S0: for (j = 0; j < 3; j++) g->c0[j] = (mkc_real)in[j]; g->s0 = (mkc_real)in[3]; break;
    case MKC_F_X: for (s = 0; s < count; s++) for (i = 0; i < m; i++) for (j = 0; j < np; j++) st->X[s][i][j] = (mkc_real)in[k++]; break;
    case MKC_F_Y: for (s = 0; s < count; s++) for (i = 0; i < m; i++) st->Y[s][i] = (mkc_real)in[k++]; break;
    case MKC_F_SLOT_AGE: set_stamps(g, in, count); break;
    case MKC_F_SLOT_CELL:
        for (s = 0; s < count; s++) {
            if (in[s] < 0 || in[s] >= MKC_CELLS)
                return MKC_BAD_INPUT;
            g->slot_cell[s] = (uint8_t)in[s];
        }
        break;
    case MKC_F_CELL_COUNT: for (j = 0; j < MKC_CELLS; j++) g->cell_count[j] = (uint16_t)in[j]; break;
    case MKC_F_MAG_FLAGS:
        g->provisional = (int32_t)in[0];
        g->failed = (int32_t)in[1];
        g->misfit = (int32_t)in[2];
        g->has_confirmed = (int32_t)in[3];
        for (j = 0; j < 3; j++)
            g->confirmed_b[j] = (mkc_real)in[4 + j];
        g->confirmed_F = (mkc_real)in[7];
        g->first_accepted_at = (int64_t)in[8];
        g->pending = 0;
        break;
    default:
        return MKC_BAD_INPUT;
    }
    return MKC_OK;
}

int mkc_build_info(long *out, int cap)
{
    long v[9];
    int i;
    v[0] = MKC_N;
    v[1] = MKC_M;
    v[2] = MKC_W;
    v[3] = MKC_K;
    v[4] = (long)sizeof(mkc_real);
    v[5] = (long)sizeof(mkc_acc);
    v[6] = (long)sizeof(mkc_ereal);
    v[7] = (long)sizeof(mkc_stream_t);
    v[8] = (long)sizeof(mkc_mag_t);
    for (i = 0; i < 9 && i < cap; i++)
        out[i] = v[i];
    return 9;
}

const mkc_mag_calibration *mkc_mag_get_calibration(const mkc_mag_t *cal, int accepted)
{
    const mkc_mag_calibration *c = accepted ? &cal->accepted : &cal->trial;
    return c->valid ? c : NULL;
}

const mkc_mag_event *mkc_mag_get_event(const mkc_mag_t *cal)
{
    return &cal->last_event;
}

int mkc_mag_get_info(const mkc_mag_t *cal, int64_t *out, int cap)
{
    int64_t v[10];
    int i;
    v[0] = cal->first_accepted_at;
    v[1] = cal->checkpoints;
    v[2] = cal->provisional;
    v[3] = cal->failed;
    v[4] = cal->pending;
    v[5] = cal->init_samples;
    v[6] = cal->policy;
    v[7] = cal->unit_ut;
    v[8] = cal->misfit;
    v[9] = cal->has_confirmed;
    for (i = 0; i < 10 && i < cap; i++)
        out[i] = v[i];
    return 10;
}
