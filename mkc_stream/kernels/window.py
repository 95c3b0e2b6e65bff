"""Streaming MKC-EM over a fixed-size window: per-sample update, E-step + rebuild every K samples.

All state lives in caller-owned arrays (mkc_stream/state.py lists them; they map one to one onto
the C struct). No kernel allocates.

Numerical form. The window's weighted normal equations A theta = b (eq. (15)) are sums of
per-row terms c x x^T with c = w / d^2. Each ring-buffer slot stores the c it added, so that
replacing a sample subtracts exactly what it added, whatever sigma/d have become since. theta is
tracked every sample in O(n^2): one step of iterative refinement with the last equilibrated
Cholesky factor of A, theta += A_f^-1 (b - A theta). Between two factorisations A changes by a
few rank-one terms out of W, so A_f^-1 A is close to I and each step removes most of the error
(and all of it once the window stops changing). The factor is refreshed every `refactor` samples
(<= K, <= W/8), at every checkpoint, and whenever a step is not small; a fresh factorisation of
a 9x9 A costs more than the step but is still cheap, and is safer than downdating A^-1 or a
Cholesky factor, which loses positive definiteness. Every K samples the E-step (Algorithm 2)
runs on the window's residuals, warm-started from the current (sigma, d), and A, b are rebuilt
from the buffer with the new weights by fixed-point rounds (Algorithm 1): the batch M-step on
the window, which also wipes the rounding drift of the add/remove updates. At a checkpoint
theta is therefore the exact batch solution; in between it is the tracked one.
"""
import math

from .._numba import kernel
from ..robust import MAD_SCALE
from . import OK, NOT_CONVERGED, SINGULAR, BAD_INPUT
from .estep import estep_channel, estep_objective
from .linalg import spd_solve
from .correntropy import gauss_weight, weight_exponent_scale

# status codes specific to the stream (continuing the kernel numbering)
WARMING_UP = 5     # fewer than min_samples in the window: theta not solved yet
REJECTED = 6       # the sample had NaN/inf and was not added

# icfg: integer configuration
I_N, I_M, I_W, I_K, I_FP_ROUNDS, I_ES_MAX_ITER, I_MIN_SAMPLES, I_REFACTOR = range(8)
N_ICFG = 8
# fcfg: float configuration
F_SIG_LO, F_SIG_HI, F_DLO, F_DHI, F_AFAC, F_FIXED_A, F_ES_GTOL, F_FP_TOL, F_SIG_START, F_SIG_PULL = range(10)
N_FCFG = 10
# cnt: int64 counters
(C_HEAD, C_COUNT, C_SEEN, C_REJECTED, C_ESTEPS, C_SINCE, C_STATUS, C_SINGULAR, C_FP_ITERS,
 C_LAST_SLOT, C_RESTARTS, C_FACTOR_AGE, C_FACTORS) = range(13)
N_COUNTERS = 13
# C_FACTOR_AGE: samples since L, D were factored from A (-1: no valid factor)
# C_FACTORS: factorisations done (checkpoints, refreshes and fall-backs)
REFINE_MAX_STEP = 0.25   # a tracking step larger than this share of |theta| means: refactor
START_SIGMA_ROBUST = 2.0  # restart_at's start bandwidth (batch.START_SIGMA_ROBUST): weights halve at ~2.4 d

# fst: float64 state scalars
S_COND, S_LAST_F = range(2)
N_FSTATE = 2


@kernel
def row_update(A, b, x, y, c, n):
    """A += c x x^T (lower triangle), b += c x y: one channel-row of eq. (15)."""
    for p in range(n):
        xp = x[p] * c
        b[p] += xp * y
        for q in range(p + 1):
            A[p, q] += xp * x[q]


@kernel
def solve_window(A, b, theta, L, D, xs, n, cnt):
    """Mirror A's lower triangle and solve A theta = b; theta is kept if A is singular.

    L, D then hold the factor the per-sample tracking steps use (age 0), or are marked invalid.
    """
    for p in range(n):
        for q in range(p + 1, n):
            A[p, q] = A[q, p]
    st, cond = spd_solve(A, b, xs, L, D, n)
    cnt[C_FACTORS] += 1
    if st == OK:
        for j in range(n):
            theta[j] = xs[j]
        cnt[C_FACTOR_AGE] = 0
    else:
        cnt[C_FACTOR_AGE] = -1
    return st, cond


@kernel
def refine_theta(A, b, theta, L, D, xs, n):
    """One refinement step theta += (D L L^T D)^-1 (b - A theta) with the stored factor (O(n^2)).

    Uses A's lower triangle only. Returns False (theta untouched) if the step is not finite or
    larger than REFINE_MAX_STEP |theta|: the factor is too stale, the caller refactors.
    """
    # r = D (b - A theta): the equilibrated residual; forward solve L z = r into xs
    for p in range(n):
        s = b[p]
        for q in range(p + 1):
            s -= A[p, q] * theta[q]
        for q in range(p + 1, n):
            s -= A[q, p] * theta[q]
        s *= D[p]
        for k in range(p):
            s -= L[p, k] * xs[k]
        xs[p] = s * L[p, p]
    # backward solve L^T y = z column by column: y_k is final once scaled, then leaves the rows
    # above (each xs[i] subtracts L[k, i] y_k in descending k). The n updates of one column are
    # independent, so the critical path is n multiply-subtracts, not the n(n-1)/2 of a row-wise dot.
    for k in range(n - 1, -1, -1):
        yk = xs[k] * L[k, k]
        xs[k] = yk
        for i in range(k):
            xs[i] -= L[k, i] * yk
    step = 0.0
    size = 0.0
    for j in range(n):
        xs[j] *= D[j]
        step = max(step, abs(xs[j]))
        size = max(size, abs(theta[j]))
    if not (step <= REFINE_MAX_STEP * size):      # also catches NaN
        return False
    for j in range(n):
        theta[j] += xs[j]
    return True


@kernel
def rebuild(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst):
    """Fixed-point rounds of Algorithm 1 on the window (eq. (16)), at most icfg[FP_ROUNDS].

    Each round: weights at the current theta -> A, b from scratch (C records each row's c) ->
    solve. Stops when ||theta_new - theta|| <= fp_tol ||theta||. Returns the status.
    """
    return rebuild_with(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst, C, False)


@kernel
def rebuild_with(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst, R, have_r):
    """rebuild(); have_r: R already holds the residuals at theta (the E-step just computed
    them with the same loop), so the first round skips that pass. Bitwise the same result."""
    n = icfg[I_N]
    m = icfg[I_M]
    count = cnt[C_COUNT]
    status = NOT_CONVERGED
    for rnd in range(icfg[I_FP_ROUNDS]):
        wsum = 0.0
        for p in range(n):
            b[p] = 0.0
            tprev[p] = theta[p]
            for q in range(n):
                A[p, q] = 0.0
        for s in range(count):
            for i in range(m):
                if have_r and rnd == 0:
                    r = R[s, i]
                else:
                    r = Y[s, i]
                    for j in range(n):
                        r -= X[s, i, j] * theta[j]
                w = gauss_weight(r * r * weight_exponent_scale(sigma[i], d[i]))   # exp(-r^2 / (2 d^2 sigma^2))
                wsum += w
                c = w * (1.0 / (d[i] * d[i]))
                C[s, i] = c
                if c != 0.0:
                    row_update(A, b, X[s, i], Y[s, i], c, n)
        if wsum < n:
            # fewer effective equations than unknowns: the kernel lost the data (a bad theta)
            cnt[C_SINGULAR] += 1
            cnt[C_FACTOR_AGE] = -1         # L, D belong to an A that no longer exists
            return SINGULAR
        st, cond = solve_window(A, b, theta, L, D, xs, n, cnt)
        fst[S_COND] = cond
        cnt[C_FP_ITERS] += 1
        if st != OK:
            cnt[C_SINGULAR] += 1
            return st
        num = 0.0
        den = 0.0
        for j in range(n):
            num += (theta[j] - tprev[j]) ** 2
            den += tprev[j] ** 2
        if math.sqrt(num) <= fcfg[F_FP_TOL] * max(math.sqrt(den), 1e-300):
            status = OK
            break
    return status


@kernel
def estep_window(icfg, fcfg, X, Y, theta, sigma, d, a, Hes, R, ebuf, cnt, fst):
    """Algorithm 2 per channel on the window's residuals at the current theta, warm-started."""
    n = icfg[I_N]
    m = icfg[I_M]
    count = cnt[C_COUNT]
    for s in range(count):
        for i in range(m):
            r = Y[s, i]
            for j in range(n):
                r -= X[s, i, j] * theta[j]
            R[s, i] = r
    Fsum = 0.0
    for i in range(m):
        amax = 0.0
        ymax = 0.0
        for s in range(count):
            ebuf[s] = R[s, i]
            amax = max(amax, abs(R[s, i]))
            ymax = max(ymax, abs(Y[s, i]))
        ai = fcfg[F_FIXED_A] if fcfg[F_FIXED_A] > 0.0 else max(fcfg[F_AFAC] * amax, 1e-12 * (1.0 + ymax))
        if not (0.5 * a[i] <= ai <= 2.0 * a[i]):
            # The truncation bound moved by more than 2x (a burst entered or left the window): the
            # objective's landscape moved with it, and the curvature learnt in the old regime
            # (e.g. ~1e6 along log sigma in the flat Gaussian regime) would throw the first step
            # to the box edge. Start this E-step from the default curvature.
            Hes[i, 0] = 0.0
            Hes[i, 1] = 0.0
            Hes[i, 2] = 0.0
            # A burst entered (a grew): restart sigma on the robust side. In the Gaussian regime the
            # likelihood's slope is O(1/sigma^2), weaker than the prior's pull (estep.py), and a
            # barrier may separate it from the robust optimum, so from sigma_hi (or 20) the E-step
            # would never see the burst; from 2 it descends to the robust optimum if the data have
            # one and climbs back to the Gaussian end if not (as MM-estimation starts robust).
            if a[i] > 0.0 and ai > 2.0 * a[i] and sigma[i] > START_SIGMA_ROBUST:      # (a = 0: first E-step)
                sigma[i] = START_SIGMA_ROBUST
        a[i] = ai
        s_new, d_new, F, its, st = estep_channel(ebuf, count, ai, sigma[i], d[i], fcfg[F_SIG_LO], fcfg[F_SIG_HI],
                                                 fcfg[F_DLO] * ai, fcfg[F_DHI] * ai, icfg[I_ES_MAX_ITER],
                                                 fcfg[F_ES_GTOL], fcfg[F_SIG_PULL], Hes[i])
        if st == OK or st == NOT_CONVERGED:
            sigma[i] = s_new
            d[i] = d_new
            Fsum += F
    fst[S_LAST_F] = Fsum
    cnt[C_ESTEPS] += 1


@kernel
def window_objective(icfg, fcfg, X, Y, theta, sigma, d, a, ebuf, cnt):
    """The E-step objective (estep.py: the window's mean negative log-likelihood of the truncated
    induced pdf, with the weak prior on sigma), summed over channels, at the current theta, sigma, d
    and truncation a: how well the estimate explains the window. Residuals formed as estep_window
    forms them (into ebuf, scratch). Non-finite when sigma, d or a are not positive."""
    n = icfg[I_N]
    m = icfg[I_M]
    count = cnt[C_COUNT]
    total = 0.0
    for i in range(m):
        if not (sigma[i] > 0.0 and d[i] > 0.0 and a[i] > 0.0) or count < 1:
            return math.inf
        for s in range(count):
            r = Y[s, i]
            for j in range(n):
                r -= X[s, i, j] * theta[j]
            ebuf[s] = r
        F, _, _ = estep_objective(math.log(sigma[i]), math.log(d[i]), ebuf, count, a[i], fcfg[F_SIG_PULL])
        total += F
    return total


@kernel
def initialise_window(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst):
    """First solve once min_samples are in: WLS (sigma = inf) on the window, then Algorithm 1."""
    n = icfg[I_N]
    m = icfg[I_M]
    count = cnt[C_COUNT]
    for p in range(n):
        b[p] = 0.0
        for q in range(n):
            A[p, q] = 0.0
    for s in range(count):
        for i in range(m):
            wd = 1.0 * (1.0 / (d[i] * d[i])) if d[i] > 0.0 else 1.0
            row_update(A, b, X[s, i], Y[s, i], wd, n)
    st, cond = solve_window(A, b, theta, L, D, xs, n, cnt)
    fst[S_COND] = cond
    if st != OK:
        cnt[C_SINGULAR] += 1
        return st
    # d unset (<= 0): start from the RMS of the WLS residuals; the first E-step refines it
    for i in range(m):
        if not d[i] > 0.0:
            acc = 0.0
            for s in range(count):
                r = Y[s, i]
                for j in range(n):
                    r -= X[s, i, j] * theta[j]
                acc += r * r
            d[i] = max(math.sqrt(acc / count), 1e-300)
    return rebuild(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst)


@kernel
def restart(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, Hes, L, D, xs, tprev, cnt, fst):
    """Forget sigma, d and theta and re-initialise from the window (WLS, then Algorithm 1)."""
    cnt[C_RESTARTS] += 1
    for i in range(icfg[I_M]):
        sigma[i] = fcfg[F_SIG_START]
        d[i] = -1.0
        Hes[i, 0] = 0.0
        Hes[i, 1] = 0.0
        Hes[i, 2] = 0.0
    return initialise_window(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst)


@kernel
def _sorted_median(e, n):
    """Median of e[:n], sorting e[:n] in place (the mean of the middle two for even n, as numpy)."""
    e[:n].sort()
    if n % 2 == 1:
        return e[n // 2]
    return (e[n // 2 - 1] + e[n // 2]) / 2.0


@kernel
def em_rounds(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, rounds, st):
    """`rounds` of Algorithm 3 on the window (E-step, then fixed-point rebuild) after a restart whose
    status is st; stops at the first failure. Returns the last status."""
    for _ in range(rounds):
        if st != OK and st != NOT_CONVERGED:
            return st
        estep_window(icfg, fcfg, X, Y, theta, sigma, d, a, Hes, R, ebuf, cnt, fst)
        st = rebuild_with(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst, R, True)
    return st


@kernel
def restart_at(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, Hes, L, D, xs, tprev, ebuf, cnt, fst, theta0):
    """restart() from a given (high-breakdown) theta0 instead of WLS, as MM-estimation starts.

    sigma starts at START_SIGMA_ROBUST and d at 1.4826 MAD of the residuals at theta0 (their RMS if
    the MAD is 0), so the first M-step keeps the start's robustness: from WLS, gross high-leverage
    outliers have already moved theta beyond what any kernel can undo.
    """
    n = icfg[I_N]
    m = icfg[I_M]
    count = cnt[C_COUNT]
    cnt[C_RESTARTS] += 1
    for j in range(n):
        theta[j] = theta0[j]
    for i in range(m):
        sigma[i] = START_SIGMA_ROBUST
        Hes[i, 0] = 0.0
        Hes[i, 1] = 0.0
        Hes[i, 2] = 0.0
        acc = 0.0
        for s in range(count):
            r = Y[s, i]
            for j in range(n):
                r -= X[s, i, j] * theta[j]
            ebuf[s] = r
            acc += r * r
        med = _sorted_median(ebuf, count)
        for s in range(count):
            ebuf[s] = abs(ebuf[s] - med)
        mad = MAD_SCALE * _sorted_median(ebuf, count)
        d[i] = max(mad if mad > 0.0 else math.sqrt(acc / count), 1e-300)
    return rebuild(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst)


@kernel
def cold_start_at(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, rounds,
                  theta0):
    """cold_start() from restart_at(theta0) (a high-breakdown start) instead of WLS."""
    st = restart_at(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, Hes, L, D, xs, tprev, ebuf, cnt, fst, theta0)
    return em_rounds(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, rounds, st)


@kernel
def cold_start(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, rounds):
    """Batch MKC-EM (Algorithm 3) on the window from scratch: restart() (WLS, then Algorithm 1 at
    the start bandwidth), then `rounds` E-step + fixed-point rounds. Returns the last status."""
    st = restart(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, Hes, L, D, xs, tprev, cnt, fst)
    return em_rounds(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, rounds, st)


@kernel(inline='always')
def learn_one(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, xk, yk, slot):
    """Feed one sample (xk (m, n), yk (m,)) into window slot `slot` (-1: the ring buffer's head).

    Returns the status of this step: OK, NOT_CONVERGED, SINGULAR, WARMING_UP or REJECTED.
    """
    n = icfg[I_N]
    m = icfg[I_M]
    W = icfg[I_W]
    # as the C port (stream.c): the slot indexes the window unchecked below, so a slot (or a
    # corrupt head/count) outside it would write past the arrays
    s = cnt[C_HEAD] if slot < 0 else slot
    if s < 0 or s >= W or s > cnt[C_COUNT] or cnt[C_COUNT] > W:
        return BAD_INPUT
    for i in range(m):
        if not math.isfinite(yk[i]):
            cnt[C_REJECTED] += 1
            return REJECTED
        for j in range(n):
            if not math.isfinite(xk[i, j]):
                cnt[C_REJECTED] += 1
                return REJECTED
    if slot < 0:
        slot = cnt[C_HEAD]
        cnt[C_HEAD] = (slot + 1) % W
    cnt[C_LAST_SLOT] = slot
    if slot < cnt[C_COUNT]:
        # replace: subtract exactly what this slot added
        for i in range(m):
            if C[slot, i] != 0.0:
                row_update(A, b, X[slot, i], Y[slot, i], -C[slot, i], n)
    else:
        cnt[C_COUNT] += 1
    ready = cnt[C_ESTEPS] > 0 or cnt[C_FP_ITERS] > 0
    for i in range(m):
        Y[slot, i] = yk[i]
        r = yk[i]
        for j in range(n):
            X[slot, i, j] = xk[i, j]
            r -= xk[i, j] * theta[j]
        c = gauss_weight(r * r * weight_exponent_scale(sigma[i], d[i])) * (1.0 / (d[i] * d[i])) if ready else 0.0
        C[slot, i] = c
        if c != 0.0:
            row_update(A, b, xk[i], yk[i], c, n)
    cnt[C_SEEN] += 1
    cnt[C_SINCE] += 1
    if cnt[C_COUNT] < icfg[I_MIN_SAMPLES]:
        cnt[C_STATUS] = WARMING_UP
        return WARMING_UP
    if not ready:
        st = initialise_window(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst)
        if st != OK and st != NOT_CONVERGED:
            cnt[C_STATUS] = st
            return st
        cnt[C_SINCE] = icfg[I_K]          # run the first E-step now
    if cnt[C_SINCE] >= icfg[I_K]:
        cnt[C_SINCE] = 0
        estep_window(icfg, fcfg, X, Y, theta, sigma, d, a, Hes, R, ebuf, cnt, fst)
        st = rebuild_with(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, L, D, xs, tprev, cnt, fst, R, True)
        if st != OK and st != NOT_CONVERGED:
            # Recovery: restart Algorithm 3 on the window from WLS and the start bandwidth, so a
            # stream never stays stuck on a degenerate estimate (its weights would all be ~0).
            st = restart(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, Hes, L, D, xs, tprev, cnt, fst)
    else:
        st = OK
        age = cnt[C_FACTOR_AGE]
        if age >= 0 and age < icfg[I_REFACTOR] and refine_theta(A, b, theta, L, D, xs, n):
            cnt[C_FACTOR_AGE] = age + 1
        else:
            st, cond = solve_window(A, b, theta, L, D, xs, n, cnt)
            fst[S_COND] = cond
            if st != OK:
                cnt[C_SINGULAR] += 1
    cnt[C_STATUS] = st
    return st


@kernel
def learn_many(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst, Xs, Ys, status_out):
    """learn_one over Xs (T, m, n), Ys (T, m) in one jitted loop; status_out (T,) int8."""
    T = Xs.shape[0]
    for t in range(T):
        status_out[t] = learn_one(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst,
                                  Xs[t], Ys[t], -1)
    return cnt[C_STATUS]
