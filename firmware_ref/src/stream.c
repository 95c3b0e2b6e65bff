/* stream.c: the generic streaming MKC-EM public API (mkc_stream/stream.py StreamingMKC). */
#include "mkc_internal.h"

void mkc_config_default(mkc_config *cfg, int n, int m)
{
    static const mkc_config defaults = MKC__CONFIG_DEFAULTS(0, 0);
    *cfg = defaults;
    cfg->n = n;
    cfg->m = m;
}

int mkc_stream_init(mkc_stream_t *st, const mkc_config *cfg, const mkc_real *sigma0, const mkc_real *d0,
                    const mkc_real *theta0)
{
    unsigned char *p = (unsigned char *)st;
    size_t k;
    int r;
    if (!st || !cfg)
        return MKC_BAD_INPUT;
    for (k = 0; k < sizeof(*st); k++)
        p[k] = 0;
    r = mkc__core_init(&st->core, cfg, sigma0, d0, theta0, 0);
    if (r != MKC_OK)
        st->core.cfg.n = 0;       /* unusable: learn_one answers MKC_BAD_INPUT */
    return r;
}

int mkc_stream_learn_one(mkc_stream_t *st, const mkc_real *x, const mkc_real *y, int slot)
{
    mkc_core_t *c = &st->core;
    int n = c->cfg.n, m = c->cfg.m, i, j;
    if (n < 1 || slot >= c->cfg.window || (slot >= 0 && slot > c->counters.count))
        return MKC_BAD_INPUT;
    for (i = 0; i < m; i++) {
        if (!(MKC_FABS_R(y[i]) <= MKC_MAX_ABS_INPUT)) {      /* NaN, inf or huge */
            c->counters.rejected += 1;
            return MKC_REJECTED;
        }
        for (j = 0; j < n; j++) {
            if (!(MKC_FABS_R(x[i * n + j]) <= MKC_MAX_ABS_INPUT)) {
                c->counters.rejected += 1;
                return MKC_REJECTED;
            }
        }
    }
    return mkc__learn_one(c, x, y, slot);
}

int mkc_stream_learn_many(mkc_stream_t *st, const mkc_real *X, const mkc_real *Y, long T, int8_t *status_out)
{
    int n = st->core.cfg.n, m = st->core.cfg.m, s = MKC_WARMING_UP;
    long t;
    for (t = 0; t < T; t++) {
        s = mkc_stream_learn_one(st, X + (size_t)t * (size_t)(m * n), Y + (size_t)t * (size_t)m, -1);
        if (status_out)
            status_out[t] = (int8_t)s;
    }
    return s;
}

void mkc_stream_predict(const mkc_stream_t *st, const mkc_real *x, mkc_real *out)
{
    int n = st->core.cfg.n, m = st->core.cfg.m, i, j;
    for (i = 0; i < m; i++) {
        mkc_real s = RC(0.0);
        for (j = 0; j < n; j++)
            s += x[i * n + j] * st->core.theta[j];
        out[i] = s;
    }
}
