/* magwindow.c: the direction-organised window of the magnetometer; kernels/magwindow.py.
 *
 * What makes a calibration window informative is orientation coverage, not recency: 72 equal-area
 * cells (6 bands uniform in z x 12 sectors of 30 degrees). Until the window is full a sample is
 * appended; then it replaces the oldest sample of the fullest cell, or of its own cell when that
 * is (one of) the fullest.
 */
#include "mkc_internal.h"

#if MKC_N_CELLS % 8 != 0
#error "magwindow.c: some_cell_fuller reads the cell counts eight at a time"
#endif

/* Cell 0..71 of a direction (need not be unit length; 0 for the zero vector): the cell of
 * (vx, vy, vz / |v|) as mkc__unit_direction_cell takes it (the band from the unit z, the sector from
 * vx, vy, whose scale the sector does not depend on), one copy of its arithmetic. */
int mkc__direction_cell(mkc_real vx, mkc_real vy, mkc_real vz)
{
    mkc_real r = MKC_SQRT_R(vx * vx + vy * vy + vz * vz);
    if (!(r > RC(0.0)))
        return 0;
    return mkc__unit_direction_cell(vx, vy, vz / r);
}

/* Four consecutive slot cells, or two consecutive cell counts, as one 32-bit word in any byte
 * order (the tests below ask only "does some byte/lane ..."). GCC and Clang make the builtin copy
 * one load on cores with unaligned loads and narrower loads on the others; elsewhere the bytes are
 * assembled. */
#if defined(__GNUC__)
static uint32_t four_cells(const uint8_t *p)
{
    uint32_t w;
    __builtin_memcpy(&w, p, sizeof w);
    return w;
}
static uint32_t two_counts(const uint16_t *p)
{
    uint32_t w;
    __builtin_memcpy(&w, p, sizeof w);
    return w;
}
#else
static uint32_t four_cells(const uint8_t *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}
static uint32_t two_counts(const uint16_t *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 16;
}
#endif

/* Whether some cell holds more than v samples. It may answer yes wrongly when a count or v is 2^15
 * or more (only in a window of W >= 2^15 samples); yes sends the caller to the full search, so
 * the slot chosen is the reference's either way. In a word of
 * two counts below 2^15, count + (0x7fff - v) sets its lane's top bit exactly when count > v and
 * never carries into the other lane; a count of 2^15 or more sets that bit itself. */
static int some_cell_fuller(const uint16_t *cc, unsigned v)
{
    const uint32_t add = (0x7fffu - v) * 0x00010001u;
    uint32_t hit = 0;
    int c;
    if (v > 0x7fffu)
        return 1;
    for (c = 0; c < MKC_N_CELLS; c += 8) {
        uint32_t w0 = two_counts(cc + c), w1 = two_counts(cc + c + 2), w2 = two_counts(cc + c + 4);
        uint32_t w3 = two_counts(cc + c + 6);
        hit |= w0 | (w0 + add) | w1 | (w1 + add) | w2 | (w2 + add) | w3 | (w3 + add);
    }
    return (hit & 0x80008000u) != 0;
}

/* The oldest of *best (stamp *best_stamp; -1: none yet) and the slots from..to-1 of cell `target`.
 * Slots are visited in increasing order and only a strictly older slot replaces the best, so ties
 * go to the lowest slot as in one full scan. */
static int older_slot(const mkc_mag_t *g, int target, int from, int to, int best, unsigned *best_stamp)
{
    int s;
    for (s = from; s < to; s++) {
        if (g->slot_cell[s] == target) {
            unsigned stamp = g->slot_stamp[s];
            if (best < 0 || stamp < *best_stamp) {
                best = s;
                *best_stamp = stamp;
            }
        }
    }
    return best;
}

/* Oldest slot of cell `target` among slot_cell[0..W-1]; -1 if none. slot_cell is read eight slots
 * at a time and only a word of four holding the target is looked at slot by slot: with
 * x = word ^ (target * 0x01010101), (x - 0x01010101) & ~x & 0x80808080 is nonzero exactly when
 * some byte of x is zero (a borrow can mark a byte only above a zero byte). */
static int oldest_slot_of_cell(const mkc_mag_t *g, int target, int W)
{
    const uint8_t *sc = g->slot_cell, *p, *end = sc + (W - W % 8);
    const uint32_t ones = 0x01010101u, highs = 0x80808080u, pattern = (uint32_t)target * ones;
    unsigned best_stamp = 0;
    int best = -1;
    p = sc;
    if (p != end) do {     /* do-while: -Os keeps a for loop's test at the top, one more branch a pass */
        uint32_t x = four_cells(p) ^ pattern, y = four_cells(p + 4) ^ pattern;
        uint32_t in_x = (x - ones) & ~x & highs, in_y = (y - ones) & ~y & highs;
        if (in_x | in_y) {
            int s = (int)(p - sc);
            if (in_x)
                best = older_slot(g, target, s, s + 4, best, &best_stamp);
            if (in_y)
                best = older_slot(g, target, s + 4, s + 8, best, &best_stamp);
        }
        p += 8;
    } while (p != end);
    return older_slot(g, target, (int)(end - sc), W, best, &best_stamp);    /* the last W % 8 slots */
}

/* Slot for a new sample of direction `cell`: the target cell's oldest slot, i.e. its smallest stamp
 * (stamps order the slots as the reference's ages do, see mkc__slot_written). The target is the
 * reference's: `cell` when its count is the largest, else the first fullest cell. */
int mkc__choose_slot(const mkc_mag_t *g, int cell, int count, int W)
{
    const uint16_t *cc = g->cell_count;
    unsigned most = 0;
    int c, target = cell;
    if (count < W)
        return count;
    if (some_cell_fuller(cc, cc[cell])) {
        for (c = 0; c < MKC_N_CELLS; c++)
            most = cc[c] > most ? cc[c] : most;
        if (cc[cell] < most)                /* the first fullest cell */
            for (target = 0; cc[target] != most; target++)
                ;
    }
    return oldest_slot_of_cell(g, target, W);
}

mkc_real mkc__calibrated_norm(const mkc_real *raw, const mkc_real *b, const mkc_real S[3][3], mkc_real *m)
{
    mkc_real v0 = raw[0] - b[0], v1 = raw[1] - b[1], v2 = raw[2] - b[2];
    mkc_real m0 = v0 * S[0][0] + v1 * S[0][1] + v2 * S[0][2];
    mkc_real m1 = v0 * S[1][0] + v1 * S[1][1] + v2 * S[1][2];
    mkc_real m2 = v0 * S[2][0] + v1 * S[2][1] + v2 * S[2][2];
    if (m) {
        m[0] = m0;
        m[1] = m1;
        m[2] = m2;
    }
    return MKC_SQRT_R(m0 * m0 + m1 * m1 + m2 * m2);
}

mkc_real mkc__raw_distance(const mkc_mag_t *g, int k, const mkc_real *c)
{
    mkc_real d0 = g->raw[k][0] - c[0], d1 = g->raw[k][1] - c[1], d2 = g->raw[k][2] - c[2];
    return MKC_SQRT_R(d0 * d0 + d1 * d1 + d2 * d2);
}

/* |S (raw_k - b)| for k < count into out: mkc__calibrated_norm's operations (one copy of them) */
void mkc__calibrated_norms(const mkc_mag_t *g, int count, const mkc_real *b, const mkc_real S[3][3], mkc_real *out)
{
    int k;
    for (k = 0; k < count; k++)
        out[k] = mkc__calibrated_norm(g->raw[k], b, S, NULL);
}

/* The cells of the window's samples around the current centre c0. */
void mkc__recount_cells(mkc_mag_t *g, int count)
{
    int c, s;
    for (c = 0; c < MKC_N_CELLS; c++)
        g->cell_count[c] = 0;
    for (s = 0; s < count; s++) {
        int cell = mkc__direction_cell(g->raw[s][0] - g->c0[0], g->raw[s][1] - g->c0[1], g->raw[s][2] - g->c0[2]);
        g->slot_cell[s] = (uint8_t)cell;
        g->cell_count[cell] += 1;
    }
}

/* Stamps 0 .. count-1 in the order of the present ones (distinct): the k-th smallest stamp is >= k,
 * so the slots renumbered so far hold 0 .. r-1 and the others still hold stamps >= r. */
static void renumber_stamps(mkc_mag_t *g, int count)
{
    int r, s;
    for (r = 0; r < count; r++) {
        int best = -1;
        for (s = 0; s < count; s++)
            if (g->slot_stamp[s] >= r && (best < 0 || g->slot_stamp[s] < g->slot_stamp[best]))
                best = s;
        g->slot_stamp[best] = (uint16_t)r;
    }
    g->next_stamp = (uint16_t)count;
}

void mkc__slot_written(mkc_mag_t *g, int slot, int count)
{
    if (g->next_stamp == UINT16_MAX)                /* once per ~65,000 samples: O(count^2) */
        renumber_stamps(g, count);
    g->slot_stamp[slot] = g->next_stamp++;
}
