/* mag.c: the live magnetometer calibrator; calib/streaming.py MagCalibrator.
 *
 * The ellipsoid model (9 parameters, one channel, target 1) fed sample by sample through the
 * streaming MKC-EM on a direction-organised window. Features are the ellipsoid's 9 terms of
 * (m - c0) / s0: (c0, s0) start from the median of the first init_samples samples (provisional),
 * move to a robust sphere fit once the window's directions cover 40% of the sphere (and the
 * estimate restarts there), and follow the trial centre and radius once a trial is accepted. Each
 * E-step checkpoint gives a trial calibration; the acceptance predicate (and, for a new
 * calibration, a cold-start batch MKC-EM on the same window that must agree) promotes it to the
 * accepted one, which alone is applied. Watchdogs return to the sphere-fit normalisation after 4
 * checkpoints without an ellipsoid or 8 trials that do not fit.
 * Size: over 600 lines: the one calibrator of calib/streaming.py (checkpoint, pool, normalisation,
 * feeding), whose parts share its state; the numerics live in the other files.
 */
#include "mkc_internal.h"

void mkc_mag_config_default(mkc_mag_config *cfg)
{
    static const mkc_mag_config defaults = {
        .stream = MKC__CONFIG_DEFAULTS(9, 1), .policy = MKC_POLICY_DIRECTION, .unit_ut = 1, .init_samples = 0,
        .rules = {.min_coverage = RC(MKC_DEF_MIN_COVERAGE), .max_condition = RC(MKC_DEF_MAX_CONDITION),
                  .max_outlier_fraction = RC(MKC_DEF_MAX_OUTLIER_FRACTION),
                  .max_residual_rel = RC(MKC_DEF_MAX_RESIDUAL_REL), .field_lo_ut = RC(MKC_DEF_FIELD_LO_UT),
                  .field_hi_ut = RC(MKC_DEF_FIELD_HI_UT), .max_disagreement_rel = RC(MKC_DEF_MAX_DISAGREEMENT_REL)},
        .switching = MKC_SWITCH_POOLED};
    *cfg = defaults;
}

int mkc_mag_init(mkc_mag_t *cal, const mkc_mag_config *cfg)
{
    mkc_config sc;
    unsigned char *p = (unsigned char *)cal;
    size_t k;
    int st, W;
    if (!cal || !cfg)
        return MKC_BAD_INPUT;
    sc = cfg->stream;
    sc.n = 9;
    sc.m = 1;
    W = sc.window;
    if (MKC_N < 9 || (cfg->policy != MKC_POLICY_FIFO && cfg->policy != MKC_POLICY_DIRECTION) ||
        cfg->init_samples < 0 || cfg->init_samples > W ||
        (cfg->switching != MKC_SWITCH_PAIRED && cfg->switching != MKC_SWITCH_POOLED))
        return MKC_BAD_INPUT;
    for (k = 0; k < sizeof(*cal); k++)
        p[k] = 0;
    st = mkc__core_init(&cal->core, &sc, NULL, NULL, NULL, 1);
    if (st != MKC_OK)
        return st;
    cal->policy = cfg->policy;
    cal->unit_ut = cfg->unit_ut != 0;
    cal->init_samples = cfg->init_samples > 0 ? cfg->init_samples : (W < MKC_DEF_INIT_SAMPLES ? W : MKC_DEF_INIT_SAMPLES);
    cal->provisional = 1;
    cal->rules = cfg->rules;
    cal->first_accepted_at = -1;
    cal->switching = cfg->switching;
    cal->last_reason.code = MKC_REASON_INITIAL;
    return MKC_OK;
}

void mkc_mag_set_listener(mkc_mag_t *cal, mkc_mag_listener fn, void *user)
{
    cal->listener = fn;
    cal->listener_user = user;
}

/* ---- normalisation ---- */

/* _set_normalisation: new (c0, s0); the features follow (they are computed from raw), the cells
 * are recounted; then either restart the estimate (WLS, E-step, rebuild) or rebuild from theta. */
static void set_normalisation(mkc_mag_t *g, const mkc_real *c0, mkc_real s0, const mkc_real *theta, int restart)
{
    int count = (int)g->core.counters.count, j;
    for (j = 0; j < 3; j++)
        g->c0[j] = c0[j];
    g->s0 = s0;
    mkc__recount_cells(g, count);
    if (restart) {
        /* (c0, s0) is the window's trimmed sphere fit: start from that sphere, the unit sphere here */
        static const mkc_creal origin[3] = {CR(0.0), CR(0.0), CR(0.0)};
        mkc_real unit[9];
        mkc__sphere_theta(origin, CR(1.0), unit);
        mkc__restart_at(&g->core, unit);
        mkc__estep_window(&g->core);
        mkc__rebuild(&g->core);
    } else {
        for (j = 0; j < 9; j++)
            g->core.theta[j] = theta[j];
        mkc__rebuild(&g->core);
    }
}

/* |a - b| in mkc_creal, each difference rounded in mkc_real first */
MKC_NOINLINE static mkc_creal distance_c(const mkc_real *a, const mkc_real *b)
{
    mkc_creal d0 = (mkc_creal)(a[0] - b[0]), d1 = (mkc_creal)(a[1] - b[1]), d2 = (mkc_creal)(a[2] - b[2]);
    return MKC_SQRT_C(d0 * d0 + d1 * d1 + d2 * d2);
}

/* _maybe_renormalise: re-centre on the trial centre and radius when they drift by > 10%. The trial
 * quadric in the new coordinates: (m - b)^T M (m - b) = 1 -> A' = F^2 M, B' = 0. */
static void maybe_renormalise(mkc_mag_t *g, const mkc__geometry *geom, const mkc_real *b, mkc_real F)
{
    mkc_creal dist = distance_c(b, g->c0), F2 = (mkc_creal)F * (mkc_creal)F;
    mkc_real theta[9];
    if (!(dist > CR(0.1) * (mkc_creal)g->s0 || MKC_FABS_C((mkc_creal)F / (mkc_creal)g->s0 - CR(1.0)) > CR(0.1)))
        return;
    theta[0] = (mkc_real)(F2 * geom->M[0][0]);
    theta[1] = (mkc_real)(F2 * geom->M[1][1]);
    theta[2] = (mkc_real)(F2 * geom->M[2][2]);
    theta[3] = (mkc_real)(CR(2.0) * (F2 * geom->M[0][1]));
    theta[4] = (mkc_real)(CR(2.0) * (F2 * geom->M[0][2]));
    theta[5] = (mkc_real)(CR(2.0) * (F2 * geom->M[1][2]));
    theta[6] = theta[7] = theta[8] = RC(0.0);
    set_normalisation(g, b, F, theta, 0);
}

/* ---- checkpoints ---- */

static void emit(mkc_mag_t *g)
{
    mkc__count(&g->checkpoints);
    if (g->listener)
        g->listener(g->listener_user, g);
}

/* The checkpoint's event: the calibration cal, or none (NULL: a checkpoint without one). */
MKC_NOINLINE static void fill_event(mkc_mag_t *g, int64_t seen, int64_t esteps, const mkc_mag_calibration *cal)
{
    mkc_mag_event *ev = &g->last_event;
    int j;
    ev->samples_seen = seen;
    ev->esteps = esteps;
    ev->accepted = cal ? cal->accepted : 0;
    ev->has_calibration = cal != NULL;
    ev->reason = g->last_reason;
    for (j = 0; j < 3; j++)
        ev->hard_iron[j] = cal ? cal->hard_iron[j] : RC(0.0);
    ev->field = cal ? cal->field : RC(0.0);
    ev->coverage = cal ? cal->quality[MKC_Q_COVERAGE] : RC(0.0);
    ev->outlier_fraction = cal ? cal->quality[MKC_Q_OUTLIER_FRACTION] : RC(0.0);
}

/* _try_final_normalisation: 1 when the sphere fit's coverage allows the final normalisation (done,
 * the checkpoint continues), 0 when still waiting (the event is filled). */
static int try_final_normalisation(mkc_mag_t *g, int count, int64_t seen, int64_t esteps)
{
    mkc_real b[3], F = RC(0.0), cov = RC(0.0), spread;
    int ok = count >= 8 && mkc__robust_sphere_fit(g, count, b, &F);
    /* a rest phase is a cloud of noise around one point, whose own sphere fit sees every direction */
    spread = ok ? mkc__sphere_spread(g, count, b, F) : RC(HUGE_VAL);
    if (ok && spread <= RC(MKC_MAX_SPHERE_SPREAD))
        cov = mkc__sphere_coverage_raw(g, count, b);
    if (!ok || spread > RC(MKC_MAX_SPHERE_SPREAD) || cov < RC(MKC_MIN_SPHERE_COVERAGE)) {
        int motion = ok && spread > RC(MKC_MAX_SPHERE_SPREAD);
        g->last_reason.code = motion ? MKC_REASON_MOTION_WAIT : MKC_REASON_COVERAGE_WAIT;
        g->last_reason.fails = 0;
        g->last_reason.v[0] = MKC_REASON_VALUE(motion ? spread : cov);
        fill_event(g, seen, esteps, NULL);
        return 0;
    }
    set_normalisation(g, b, F, NULL, 1);
    g->provisional = 0;
    return 1;
}

/* _needs_confirmation: a trial that passes the gates is confirmed by a cold start unless it is the
 * calibration confirmed last (within the disagreement tolerance): steady streams pay nothing. */
static int needs_confirmation(const mkc_mag_t *g, const mkc_real *b, mkc_real F)
{
    mkc_creal tol;
    if (!g->has_confirmed)
        return 1;
    tol = (mkc_creal)g->rules.max_disagreement_rel * MKC_FABS_C((mkc_creal)F);
    return !(distance_c(b, g->confirmed_b) <= tol && MKC_FABS_C((mkc_creal)(F - g->confirmed_F)) <= tol);
}

/* The cold-start check runs in the estimate's own state and keeps the warm one meanwhile in its
 * weights' bytes: A .. fit go into C's bytes (the part beyond them into saved_tail) and the cold
 * start's rebuilds leave C alone. The weights are not kept: at a checkpoint they are what the last
 * rebuild round recorded (at tprev, sigma, d), recomputed to the same bits afterwards. Returns 0,
 * keeping nothing, when C is not that (a rebuild failed and the restart after it stopped before
 * rebuilding, or fp_rounds = 0): the check is not run then. */
static int keep_warm_estimate(mkc_mag_t *g)
{
    mkc_core_t *c = &g->core;
    const unsigned char *src = (const unsigned char *)(void *)c + offsetof(mkc_core_t, A);
    unsigned char *inC = (unsigned char *)(void *)c->C;
    size_t k;
    if (!mkc__weights_recorded(c))
        return 0;
    for (k = 0; k < MKC_CORE_SAVED_BYTES; k++) {
        if (k < MKC_CORE_C_BYTES)
            inC[k] = src[k];
        else
            g->saved_tail[k - MKC_CORE_C_BYTES] = src[k];
    }
    c->defer_weights = 1;
    return 1;
}

/* n bytes of the kept estimate from byte `offset` of mkc_core_t (a field from A .. fit) into to. */
static void kept_bytes(const mkc_mag_t *g, size_t offset, void *to, size_t n)
{
    const unsigned char *inC = (const unsigned char *)(const void *)g->core.C;
    unsigned char *dst = (unsigned char *)to;
    size_t k, from = offset - offsetof(mkc_core_t, A);
    for (k = 0; k < n; k++)
        dst[k] = from + k < MKC_CORE_C_BYTES ? inC[from + k] : g->saved_tail[from + k - MKC_CORE_C_BYTES];
}

/* The check agreed: the warm estimate back, bytes for bytes, and its weights recomputed. */
static void restore_warm_estimate(mkc_mag_t *g)
{
    mkc_core_t *c = &g->core;
    kept_bytes(g, offsetof(mkc_core_t, A), (unsigned char *)(void *)c + offsetof(mkc_core_t, A),
               MKC_CORE_SAVED_BYTES);
    mkc__record_weights_at(c, c->tprev, c->sigma, c->d);
    c->defer_weights = 0;
}

/* The stream continues from the cold start: its weights are those its last rebuild round would
 * have recorded; where no round ran (a cold start that stopped before any) the warm ones, as C was
 * then left alone, recomputed from the kept tprev, sigma, d. */
static void keep_cold_estimate(mkc_mag_t *g)
{
    mkc_core_t *c = &g->core;
    if (c->defer_weights == 2) {
        mkc__record_weights_at(c, c->tprev, c->sigma, c->d);
    } else {
        mkc_real th[MKC_N], sg[MKC_M], dd[MKC_M];
        kept_bytes(g, offsetof(mkc_core_t, tprev), th, sizeof th);
        kept_bytes(g, offsetof(mkc_core_t, sigma), sg, sizeof sg);
        kept_bytes(g, offsetof(mkc_core_t, d), dd, sizeof dd);
        mkc__record_weights_at(c, th, sg, dd);
    }
    c->defer_weights = 0;
}

/* The kept warm estimate back into A .. fit for another cold start from it; C still keeps it. */
MKC_NOINLINE static void reload_warm_estimate(mkc_mag_t *g)
{
    kept_bytes(g, offsetof(mkc_core_t, A), (unsigned char *)(void *)&g->core + offsetof(mkc_core_t, A),
               MKC_CORE_SAVED_BYTES);
    g->core.defer_weights = 1;
}

/* A cold start's score: the window objective at its end (HUGE_VAL if it ended singular or
 * non-finite). */
MKC_NOINLINE static mkc_ereal cold_score(mkc_core_t *c, int status)
{
    mkc_ereal f;
    if (status != MKC_OK && status != MKC_NOT_CONVERGED)
        return EC(HUGE_VAL);
    f = mkc__window_objective(c);
    return isfinite(f) ? f : EC(HUGE_VAL);
}

/* _better_cold_start (calib/streaming.py): batch MKC-EM from the sphere start theta0 and from WLS,
 * each from the kept warm estimate; the estimate is left at the one with the lower window objective
 * (the sphere start on a tie). There is no room for a second estimate, so WLS runs first and is run
 * again (the same bits) when it wins, which is the rarer outcome. */
static void better_cold_start(mkc_mag_t *g, const mkc_real *theta0)
{
    mkc_ereal f_wls = cold_score(&g->core, mkc__cold_start(&g->core, MKC_COLD_START_ROUNDS)), f_sphere;
    reload_warm_estimate(g);
    f_sphere = cold_score(&g->core, mkc__cold_start_at(&g->core, MKC_COLD_START_ROUNDS, theta0));
    if (f_wls < f_sphere) {
        reload_warm_estimate(g);
        (void)mkc__cold_start(&g->core, MKC_COLD_START_ROUNDS);
    }
}

/* The calibration (b, S, F) of a geometry into cal, and its quality figures on the window. */
static void calibration_of(mkc_mag_t *g, int count, const mkc_creal *bd, const mkc_creal Sd[3][3], mkc_creal Fd,
                           mkc_mag_calibration *cal)
{
    int j, k;
    for (j = 0; j < 3; j++) {
        cal->hard_iron[j] = (mkc_real)bd[j];
        for (k = 0; k < 3; k++)
            cal->soft_iron[j][k] = (mkc_real)Sd[j][k];
    }
    cal->field = (mkc_real)Fd;
    mkc__quality_figures(g, count, cal->hard_iron, (const mkc_real(*)[3])cal->soft_iron, cal->field,
                         mkc__weighted_condition(g, count), cal->quality);
}

/* _cold_start_disagreement: batch MKC-EM from scratch on the window, in the estimate's own state.
 * Returns the disagreement max(|b_cold - b|, |F_cold - F|) (HUGE_VAL when the cold start gives no
 * ellipsoid, or is not run because the warm weights could not be recomputed: keep_warm_estimate;
 * the reference runs it there). If it agrees, the warm estimate is restored (nothing changes);
 * otherwise the stream continues from the cold start and *have_cold says whether cold holds its
 * calibration (b, S, F and quality). */
static mkc_creal cold_start_disagreement(mkc_mag_t *g, int count, const mkc_real *b, mkc_real F, int *have_cold,
                                         mkc_mag_calibration *cold)
{
    mkc__geometry geom;
    mkc_mag_reason unused;
    mkc_creal bd[3], Sd[3][3], Fd, e0, e1, e2, dis, dF, sc[3];
    mkc_real sb[3], sF = RC(0.0), theta0[9];
    int j, have_sphere = 0;
    *have_cold = 0;
    /* from the window's own trimmed sphere (a high-breakdown start, independent of the warm trial)
     * and from WLS, the one the window's likelihood prefers kept (better_cold_start); only WLS when
     * the window gives no sphere around the features' origin */
    if (count >= 8 && mkc__robust_sphere_fit(g, count, sb, &sF)) {
        for (j = 0; j < 3; j++)
            sc[j] = (mkc_creal)((sb[j] - g->c0[j]) / g->s0);
        have_sphere = mkc__sphere_theta(sc, (mkc_creal)(sF / g->s0), theta0);
    }
    if (!keep_warm_estimate(g))
        return CR(HUGE_VAL);
    if (have_sphere)
        better_cold_start(g, theta0);
    else
        mkc__cold_start(&g->core, MKC_COLD_START_ROUNDS);
    if (mkc__geometry_from_theta(g->core.theta, &geom, &unused) != MKC_REASON_NONE) {
        keep_cold_estimate(g);
        return CR(HUGE_VAL);
    }
    mkc__raw_geometry(&geom, g->c0, g->s0);
    mkc__calibration_from_geometry(&geom, bd, Sd, &Fd);
    e0 = bd[0] - (mkc_creal)b[0];
    e1 = bd[1] - (mkc_creal)b[1];
    e2 = bd[2] - (mkc_creal)b[2];
    dis = MKC_SQRT_C(e0 * e0 + e1 * e1 + e2 * e2);
    dF = MKC_FABS_C(Fd - (mkc_creal)F);
    dis = dF > dis ? dF : dis;
    if (dis <= (mkc_creal)g->rules.max_disagreement_rel * MKC_FABS_C((mkc_creal)F)) {
        restore_warm_estimate(g);
        return dis;
    }
    keep_cold_estimate(g);
    calibration_of(g, count, bd, (const mkc_creal(*)[3])Sd, Fd, cold);
    *have_cold = 1;
    return dis;
}

/* _pool_fits (calib/streaming.py): 1 when the accepted calibration passes the fit gates (outlier
 * fraction, residual) on the window, judged as a trial would be (the window's condition is the
 * trial's: it does not depend on the calibration). */
static int pool_fits(mkc_mag_t *g, int count, const mkc_mag_calibration *cal)
{
    const mkc_mag_calibration *a = &g->accepted;
    mkc_real q[MKC_QUALITY];
    mkc_mag_reason reason;
    mkc__quality_figures(g, count, a->hard_iron, (const mkc_real(*)[3])a->soft_iron, a->field,
                         cal->quality[MKC_Q_CONDITION], q);
    return !(mkc__acceptance_check(g, q, a->field, -CR(1.0), &reason) & (MKC_FAIL_RESIDUAL | MKC_FAIL_OUTLIERS));
}

/* _offer_pooled (calib/streaming.py): the accepted calibration is the running mean of the trials
 * p_i = (b_i, S_i, F_i) that joined the pool, p <- p + (p_i - p) / min(n, N), N = MKC_POOL_WINDOWS W / K.
 * A trial joins unless the window supports it over the pool and it lies farther than
 * max_disagreement_rel * F from it, or supports it strongly (gain > Z_RESTART se); W / K such trials in
 * a row restart the pool from the latest.
 * While the pool holds fewer than W / K trials, or when the pool fails the window's fit gates
 * (pool_fits), a trial the window supports replaces it; so does a strongly supported trial that fits
 * its inliers DOMINANCE times better than the pool (supports_switch's 3: the pool is a wrong mode). */
static void offer_pooled(mkc_mag_t *g, int count, const mkc_mag_calibration *cal)
{
    mkc_acc member[13], n_cap, S[3][3], det, c;
    int per_window = g->core.cfg.window / g->core.cfg.estep_every, i, j;
    mkc_mag_calibration *a = &g->accepted;
    if (per_window < 1)
        per_window = 1;
    for (i = 0; i < 3; i++) {
        member[i] = (mkc_acc)cal->hard_iron[i];
        for (j = 0; j < 3; j++)
            member[3 + 3 * i + j] = (mkc_acc)cal->soft_iron[i][j];
    }
    member[12] = (mkc_acc)cal->field;
    if (g->pool_n > 0) {
        int support = mkc__supports_switch(g, count, cal, a), better = support >= 1, strong = support >= 2;
        int dominant = support == 3;   /* a wrong mode: the strongly supported trial fits DOMINANCE times better */
        mkc_acc tol = (mkc_acc)g->rules.max_disagreement_rel * MKC_FABS_A(g->pool_mean[12]);
        mkc_acc d0 = member[0] - g->pool_mean[0], d1 = member[1] - g->pool_mean[1], d2 = member[2] - g->pool_mean[2];
        int far = MKC_SQRT_A(d0 * d0 + d1 * d1 + d2 * d2) > tol || MKC_FABS_A(member[12] - g->pool_mean[12]) > tol;
        /* a young pool, or one that no longer fits the window: the paired rule, the better trial replaces it */
        if ((better && (g->pool_n < per_window || !pool_fits(g, count, cal))) || dominant) {
            g->pool_n = 0;
        } else if (strong || (better && far)) {
            g->pool_streak += 1;
            if (g->pool_streak < per_window)
                return;
            g->pool_n = 0;             /* the data moved on: start again from this trial */
        }
    }
    g->pool_streak = 0;
    g->pool_n += 1;
    n_cap = (mkc_acc)(g->pool_n < MKC_POOL_WINDOWS * per_window ? g->pool_n : MKC_POOL_WINDOWS * per_window);
    for (i = 0; i < 13; i++)
        g->pool_mean[i] += (member[i] - g->pool_mean[i]) / n_cap;
    /* det_one (calib/streaming.py): S' = sym(S) / c, F' = F / c, c = det(sym(S))^(1/3), so det S' = 1 */
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++)
            S[i][j] = AC(0.5) * (g->pool_mean[3 + 3 * i + j] + g->pool_mean[3 + 3 * j + i]);
    det = S[0][0] * (S[1][1] * S[2][2] - S[1][2] * S[2][1]) - S[0][1] * (S[1][0] * S[2][2] - S[1][2] * S[2][0])
          + S[0][2] * (S[1][0] * S[2][1] - S[1][1] * S[2][0]);
    c = MKC_EXP_A(MKC_LOG_A(det) / AC(3.0));
    *a = *cal;
    for (i = 0; i < 3; i++) {
        a->hard_iron[i] = (mkc_real)g->pool_mean[i];
        for (j = 0; j < 3; j++)
            a->soft_iron[i][j] = (mkc_real)(S[i][j] / c);
    }
    a->field = (mkc_real)(g->pool_mean[12] / c);
}

/* The accepted calibration (restored from storage, persist.c) as the pool's one member: a young pool,
 * so a trial the window supports over it replaces it and the others average with it. */
void mkc__seed_pool(mkc_mag_t *g)
{
    const mkc_mag_calibration *a = &g->accepted;
    int i, j;
    for (i = 0; i < 3; i++) {
        g->pool_mean[i] = (mkc_acc)a->hard_iron[i];
        for (j = 0; j < 3; j++)
            g->pool_mean[3 + 3 * i + j] = (mkc_acc)a->soft_iron[i][j];
    }
    g->pool_mean[12] = (mkc_acc)a->field;
    g->pool_n = 1;
    g->pool_streak = 0;
}

/* _offer: a passing trial replaces the accepted calibration only when the window supports it as the
 * better fit (calib/confidence.py), or joins the pool (offer_pooled) */
static void offer(mkc_mag_t *g, int count, const mkc_mag_calibration *cal, int64_t seen)
{
    if (g->switching == MKC_SWITCH_POOLED)
        offer_pooled(g, count, cal);
    else if (!g->accepted.valid || mkc__supports_switch(g, count, cal, &g->accepted))
        g->accepted = *cal;
    else
        return;
    if (g->first_accepted_at < 0)
        g->first_accepted_at = seen;
}

static void checkpoint(mkc_mag_t *g)
{
    int64_t seen = g->core.counters.seen, esteps = g->core.counters.esteps;
    int count = (int)g->core.counters.count, why, j;
    mkc__geometry geom;
    mkc_mag_reason reason;
    mkc_creal bd[3], Sd[3][3], Fd;
    mkc_real sigma, d;
    mkc_mag_calibration *cal = &g->trial;
    uint32_t fails;
    if (g->provisional) {
        /* The first centre came from a few samples, possibly all on one patch of the surface: the
         * "= 1" form of eq. (36) degenerates when the features' origin is on the ellipsoid. A
         * sphere fit is well-posed anywhere; once the window's directions around it cover enough
         * of the sphere, re-centre the features there and restart the estimate. */
        if (!try_final_normalisation(g, count, seen, esteps)) {
            emit(g);
            return;
        }
    }
    sigma = g->core.sigma[0];
    d = g->core.d[0];
    reason.code = MKC_REASON_NONE;
    reason.fails = 0;
    for (j = 0; j < 6; j++)
        reason.v[j] = 0;
    why = mkc__geometry_from_theta(g->core.theta, &geom, &reason);
    if (why != MKC_REASON_NONE) {
        reason.code = why;
        g->last_reason = reason;
        fill_event(g, seen, esteps, NULL);
        g->failed += 1;
        if (g->failed >= MKC_MAX_FAILED_CHECKPOINTS) {
            /* watchdog: a bad normalisation (features centred on the surface) cannot heal itself;
             * go back to the sphere-fit normalisation on the current window */
            g->provisional = 1;
            g->failed = 0;
        }
        emit(g);
        return;
    }
    mkc__raw_geometry(&geom, g->c0, g->s0);
    mkc__calibration_from_geometry(&geom, bd, Sd, &Fd);
    g->failed = 0;
    /* the trial is built in place: nothing reads g->trial until the checkpoint's end */
    calibration_of(g, count, bd, (const mkc_creal(*)[3])Sd, Fd, cal);
    fails = mkc__acceptance_check(g, cal->quality, cal->field, -CR(1.0), &reason);
    if (!fails && needs_confirmation(g, cal->hard_iron, cal->field)) {
        /* A warm-started estimate can lock onto a wrong mode that it reinforces (the samples it
         * down-weights are the ones that would correct it); a cold start cannot inherit that. */
        mkc_mag_calibration cold;
        int have_cold;
        mkc_creal dis = cold_start_disagreement(g, count, cal->hard_iron, cal->field, &have_cold, &cold);
        fails = mkc__acceptance_check(g, cal->quality, cal->field, dis, &reason);
        if (!fails) {
            for (j = 0; j < 3; j++)
                g->confirmed_b[j] = cal->hard_iron[j];
            g->confirmed_F = cal->field;
            g->has_confirmed = 1;
        } else if (have_cold) {          /* report (and continue from) the cold start */
            *cal = cold;                 /* b, S, F, quality; the rest is set below */
            sigma = g->core.sigma[0];
            d = g->core.d[0];
        }
    }
    /* Watchdog: trials that keep failing the fit gates mean the estimate no longer fits the window
     * (e.g. a wrong mode after a disturbance): redo the normalisation and restart. */
    if (fails & (MKC_FAIL_RESIDUAL | MKC_FAIL_OUTLIERS))
        g->misfit += 1;
    else
        g->misfit = 0;
    if (g->misfit >= MKC_MAX_MISFIT_TRIALS) {
        g->misfit = 0;
        g->provisional = 1;
    }
    cal->sigma = sigma;
    cal->d = d;
    cal->valid = 1;
    cal->accepted = fails == 0;
    cal->reason = reason;
    cal->samples_seen = seen;
    cal->esteps = esteps;
    /* _offer: a passing trial reaches the accepted calibration */
    if (!fails)
        offer(g, count, cal, seen);
    g->last_reason = reason;
    fill_event(g, seen, esteps, cal);
    if (!fails)              /* only a trustworthy trial may move the feature normalisation */
        maybe_renormalise(g, &geom, cal->hard_iron, cal->field);
    emit(g);
}

/* ---- feeding ---- */

/* finite, and small enough that sums of squares stay finite (the reference accepts any finite
 * value; a median of values near the overflow limit would put inf into c0) */
static int finite3(mkc_real x, mkc_real y, mkc_real z)
{
    return MKC_FABS_R(x) <= MKC_MAX_ABS_INPUT && MKC_FABS_R(y) <= MKC_MAX_ABS_INPUT
           && MKC_FABS_R(z) <= MKC_MAX_ABS_INPUT;
}

/* One sample through the window (kernels/magwindow.py mag_learn_many's loop body), then the
 * checkpoint if it ran an E-step. The caller has checked the sample (finite3). */
static int feed(mkc_mag_t *g, mkc_real mx, mkc_real my, mkc_real mz)
{
    mkc_core_t *c = &g->core;
    mkc_real xk[9], yk[1] = {RC(1.0)};
    int W = c->cfg.window, cell, count, slot, st, j;
    int64_t esteps;
    mkc__ellipsoid_features(mx, my, mz, g->c0, g->s0, xk);
    /* bounded normalised coordinates keep every product of features finite (Python: any finite) */
    for (j = 6; j < 9; j++) {
        if (!(MKC_FABS_R(xk[j]) <= MKC_MAX_ABS_NORMALISED)) {
            mkc__count(&c->counters.rejected);
            return MKC_REJECTED;
        }
    }
    cell = mkc__direction_cell(mx - g->c0[0], my - g->c0[1], mz - g->c0[2]);
    count = (int)c->counters.count;
    if (g->policy == MKC_POLICY_FIFO) {
        slot = (int)c->counters.head;
        c->counters.head = (slot + 1) % W;
    } else {
        slot = mkc__choose_slot(g, cell, count, W);
    }
    if (slot < count)
        g->cell_count[g->slot_cell[slot]] -= 1;
    esteps = c->counters.esteps;
    g->in_raw[0] = mx;
    g->in_raw[1] = my;
    g->in_raw[2] = mz;
    st = mkc__learn_one(c, xk, yk, slot);
    g->slot_cell[slot] = (uint8_t)cell;
    mkc__slot_written(g, slot, count);
    g->cell_count[cell] += 1;
    if (c->counters.esteps > esteps && c->counters.status != MKC_WARMING_UP && c->counters.since == 0)
        checkpoint(g);
    return st;
}

/* Median of the per-axis values of the pending samples (held in raw[0..pending-1]). */
static void first_normalisation(mkc_mag_t *g)
{
    int n = g->pending, k;
    mkc_real *w = g->core.ebuf;               /* free: no E-step yet */
    mkc__axis_medians(g, n, g->c0);
    for (k = 0; k < n; k++)
        w[k] = mkc__raw_distance(g, k, g->c0);
    g->s0 = mkc__median(w, n);
    if (!(g->s0 != RC(0.0)))               /* "or 1.0" */
        g->s0 = RC(1.0);
}

int mkc_mag_push(mkc_mag_t *cal, mkc_real mx, mkc_real my, mkc_real mz)
{
    int k, st = MKC_WARMING_UP;
    if (!finite3(mx, my, mz)) {
        mkc__count(&cal->core.counters.rejected);
        return MKC_REJECTED;
    }
    if (cal->s0 > RC(0.0))
        return feed(cal, mx, my, mz);
    /* gather init_samples finite samples for the first normalisation; raw[] holds them (each
     * goes back to its own slot: the window is empty, so slot k = sample k) */
    cal->raw[cal->pending][0] = mx;
    cal->raw[cal->pending][1] = my;
    cal->raw[cal->pending][2] = mz;
    cal->pending += 1;
    if (cal->pending < cal->init_samples)
        return MKC_WARMING_UP;
    first_normalisation(cal);
    for (k = 0; k < cal->pending; k++) {
        mkc_real x = cal->raw[k][0], y = cal->raw[k][1], z = cal->raw[k][2];
        st = feed(cal, x, y, z);
    }
    cal->pending = 0;
    return st;
}

int mkc_mag_push_many(mkc_mag_t *cal, const mkc_real *mags, long T, int8_t *status_out)
{
    long t;
    int st = MKC_WARMING_UP;
    for (t = 0; t < T; t++) {
        st = mkc_mag_push(cal, mags[3 * t], mags[3 * t + 1], mags[3 * t + 2]);
        if (status_out)
            status_out[t] = (int8_t)st;
    }
    return st;
}

/* ---- use ---- */

int mkc_mag_apply(const mkc_mag_t *cal, const mkc_real raw[3], mkc_real out[3])
{
    const mkc_mag_calibration *a = &cal->accepted;
    if (!a->valid)
        return MKC_NOT_CALIBRATED;
    /* out = S (raw - b): the checkpoint code's calibrated vector (its norm unused) */
    (void)mkc__calibrated_norm(raw, a->hard_iron, (const mkc_real(*)[3])a->soft_iron, out);
    return MKC_OK;
}

void mkc_mag_status_reason(const mkc_mag_t *cal, mkc_mag_reason *out)
{
    int j;
    out->fails = 0;
    for (j = 0; j < 6; j++)
        out->v[j] = 0;
    if (!(cal->s0 > RC(0.0))) {
        out->code = MKC_REASON_PENDING;
        out->v[0] = MKC_REASON_VALUE(cal->pending);
        out->v[1] = MKC_REASON_VALUE(cal->init_samples);
    } else if (cal->core.counters.status == MKC_WARMING_UP) {
        out->code = MKC_REASON_WINDOW;
        out->v[0] = MKC_REASON_VALUE((int32_t)cal->core.counters.count);   /* <= W */
        out->v[1] = MKC_REASON_VALUE(cal->core.cfg.min_samples);
    } else if (cal->core.counters.esteps == 0 && cal->core.counters.status == MKC_SINGULAR) {
        out->code = MKC_REASON_DEGENERATE;      /* no checkpoint can come: samples on a curve or a plane */
    } else {
        *out = cal->last_reason;
    }
}

void mkc_mag_counts(const mkc_mag_t *cal, int64_t *samples, int64_t *bad_frames)
{
    *samples = cal->core.counters.seen + cal->core.counters.rejected + cal->pending;
    *bad_frames = cal->core.counters.rejected;
}
