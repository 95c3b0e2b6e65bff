"""Magnetometer feeding of the streaming window: features, direction cells, slot choice.

What makes a calibration window informative is orientation coverage, not recency (design notes):
a hand-held sweep covers the sphere in tens of seconds, so the last W samples at 50-100 Hz may
all point one way. The window is therefore organised by direction, like the embedded peers' cell
buffers: 72 equal-area cells (6 bands uniform in z x 12 sectors of 30 degrees). Until the window
is full a sample is appended; then it replaces the oldest sample of the fullest cell, or of its
own cell when that is (one of) the fullest. Fixed size, part of the state, and the stream still
equals the batch solver on the window's contents.
"""
import math

from .._numba import kernel
from . import window as K

N_BANDS = 6
N_SECTORS = 12
N_CELLS = N_BANDS * N_SECTORS


@kernel
def direction_cell(vx, vy, vz):
    """Cell 0..71 of a direction (need not be unit length; 0 for the zero vector)."""
    r = math.sqrt(vx * vx + vy * vy + vz * vz)
    if not r > 0.0:
        return 0
    z = min(max(vz / r, -1.0), 1.0)
    band = min(int((z + 1.0) * 0.5 * N_BANDS), N_BANDS - 1)
    lon = math.atan2(vy, vx) + math.pi
    sector = min(int(lon / (2.0 * math.pi) * N_SECTORS), N_SECTORS - 1)
    return band * N_SECTORS + sector


@kernel
def ellipsoid_features(mx, my, mz, c0, s0, xk):
    """x_k of eq. (36)-(37) for the normalised sample (m - c0)/s0, into xk (1, 9)."""
    x = (mx - c0[0]) / s0
    y = (my - c0[1]) / s0
    z = (mz - c0[2]) / s0
    xk[0, 0] = x * x
    xk[0, 1] = y * y
    xk[0, 2] = z * z
    xk[0, 3] = x * y
    xk[0, 4] = x * z
    xk[0, 5] = y * z
    xk[0, 6] = x
    xk[0, 7] = y
    xk[0, 8] = z


@kernel
def choose_slot(cell, count, W, slot_cell, slot_age, cell_count):
    """Slot for a new sample of direction `cell` (see module doc). Returns the slot index."""
    if count < W:
        return count
    fullest = 0
    for c in range(N_CELLS):
        if cell_count[c] > cell_count[fullest]:
            fullest = c
    target = cell if cell_count[cell] >= cell_count[fullest] else fullest
    best = -1
    best_age = 0
    for s in range(W):
        if slot_cell[s] == target and (best < 0 or slot_age[s] < best_age):
            best = s
            best_age = slot_age[s]
    return best


@kernel
def mag_learn_many(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst,
                   raw, slot_cell, slot_age, cell_count, c0, s0, policy, mags, start, status_out, xk, yk):
    """Feed mags[start:] until the end or just after an E-step checkpoint.

    policy 0: ring buffer (FIFO); 1: direction cells. raw (W, 3) keeps each slot's raw sample so
    features can be recomputed when the normalisation changes. Returns the index after the last
    sample consumed.
    """
    T = mags.shape[0]
    W = icfg[K.I_W]
    yk[0] = 1.0
    t = start
    while t < T:
        mx = mags[t, 0]
        my = mags[t, 1]
        mz = mags[t, 2]
        if not (math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz)):
            cnt[K.C_REJECTED] += 1
            status_out[t] = K.REJECTED
            t += 1
            continue
        ellipsoid_features(mx, my, mz, c0, s0, xk)
        finite = True
        for j in range(9):
            finite = finite and math.isfinite(xk[0, j])
        if not finite:
            # a huge sample whose features overflow: rejected before it touches the slot bookkeeping
            # (learn_one would reject it after the cells and raw had been updated)
            cnt[K.C_REJECTED] += 1
            status_out[t] = K.REJECTED
            t += 1
            continue
        cell = direction_cell(mx - c0[0], my - c0[1], mz - c0[2])
        count = cnt[K.C_COUNT]
        if policy == 0:
            slot = cnt[K.C_HEAD]
            cnt[K.C_HEAD] = (slot + 1) % W
        else:
            slot = choose_slot(cell, count, W, slot_cell, slot_age, cell_count)
        if slot < count:
            cell_count[slot_cell[slot]] -= 1
        esteps = cnt[K.C_ESTEPS]
        st = K.learn_one(icfg, fcfg, X, Y, C, A, b, theta, sigma, d, a, Hes, L, D, xs, tprev, R, ebuf, cnt, fst,
                         xk, yk, slot)
        raw[slot, 0] = mx
        raw[slot, 1] = my
        raw[slot, 2] = mz
        slot_cell[slot] = cell
        slot_age[slot] = cnt[K.C_SEEN]
        cell_count[cell] += 1
        status_out[t] = st
        t += 1
        if cnt[K.C_ESTEPS] > esteps:
            break
    return t


@kernel
def refeature_window(X, raw, count, c0, s0, xk):
    """Recompute every window slot's features under a new normalisation (c0, s0)."""
    for s in range(count):
        ellipsoid_features(raw[s, 0], raw[s, 1], raw[s, 2], c0, s0, xk)
        for j in range(9):
            X[s, 0, j] = xk[0, j]


@kernel
def recount_cells(raw, count, c0, slot_cell, cell_count):
    for c in range(N_CELLS):
        cell_count[c] = 0
    for s in range(count):
        cell = direction_cell(raw[s, 0] - c0[0], raw[s, 1] - c0[1], raw[s, 2] - c0[2])
        slot_cell[s] = cell
        cell_count[cell] += 1
