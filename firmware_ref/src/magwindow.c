/* magwindow.c: the direction-organised window of the magnetometer; kernels/magwindow.py.
 *
 * What makes a calibration window informative is orientation coverage, not recency: 72 equal-area
 * cells (6 bands uniform in z x 12 sectors of 30 degrees). Until the window is full a sample is
 * appended; then it replaces the oldest sample of the fullest cell, or of its own cell when that
 * is (one of) the fullest.
 */
#include "mkc_internal.h"

/* Cell 0..71 of a direction (need not be unit length; 0 for the zero vector). */
int mkc__direction_cell(mkc_real vx, mkc_real vy, mkc_real vz)
{
    mkc_real r = MKC_SQRT_R(vx * vx + vy * vy + vz * vz);
    mkc_real z, lon;
    int band, sector;
    if (!(r > RC(0.0)))
        return 0;
    z = mkc__min_r(mkc__max_r(vz / r, RC(-1.0)), RC(1.0));
    band = (int)((z + RC(1.0)) * RC(0.5) * RC(MKC_N_BANDS));
    band = band < MKC_N_BANDS - 1 ? band : MKC_N_BANDS - 1;
    lon = MKC_ATAN2_R(vy, vx) + RC(MKC_PI);
    sector = (int)(lon / (RC(2.0) * RC(MKC_PI)) * RC(MKC_N_SECTORS));
    sector = sector < MKC_N_SECTORS - 1 ? sector : MKC_N_SECTORS - 1;
    return band * MKC_N_SECTORS + sector;
}

/* Slot for a new sample of direction `cell`. slot_age holds the low 32 bits of the samples seen
 * when each slot was written; "oldest" is the largest age counted back from now, which orders the
 * slots as the reference's int64 ages do while no sample stays in the window for 2^32 samples. */
int mkc__choose_slot(const mkc_mag_t *g, int cell, int count, int W)
{
    int c, s, fullest = 0, target, best = -1;
    uint32_t now = (uint32_t)g->core.counters.seen, best_age = 0;
    if (count < W)
        return count;
    for (c = 0; c < MKC_N_CELLS; c++)
        if (g->cell_count[c] > g->cell_count[fullest])
            fullest = c;
    target = g->cell_count[cell] >= g->cell_count[fullest] ? cell : fullest;
    for (s = 0; s < W; s++) {
        if (g->slot_cell[s] == target) {
            uint32_t age = now - g->slot_age[s];    /* modular: how long ago */
            if (best < 0 || age > best_age) {
                best = s;
                best_age = age;
            }
        }
    }
    return best;
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
