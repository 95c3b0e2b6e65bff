/* mkc_introspect.h: read and write any field of a state, and the build's facts.
 *
 * For the C self-test, the host tools (mkc_replay) and the Python bridge (mkc_stream/cport), which
 * compare the port with the Python reference field by field and restart it from a reference state.
 * Firmware needs only mkc.h. The field ids are mirrored by mkc_stream/cport/bindings.py (F_*);
 * tests/test_firmware.py checks that both lists agree.
 */
#ifndef MKC_INTROSPECT_H
#define MKC_INTROSPECT_H

#include "mkc.h"

#ifdef __cplusplus
extern "C" {
#endif

enum {  /* mkc_get / mkc_set fields; window-sized fields cover the count samples in the window */
    MKC_F_THETA = 0, MKC_F_SIGMA, MKC_F_D, MKC_F_A, MKC_F_HES, MKC_F_C, MKC_F_COND, MKC_F_LAST_F,
    MKC_F_CNT, MKC_F_NORMAL_A, MKC_F_NORMAL_B, MKC_F_RAW, MKC_F_C0S0, MKC_F_X, MKC_F_Y,
    MKC_F_L, MKC_F_DEQ, MKC_F_XS, MKC_F_TPREV, MKC_F_SLOT_AGE, MKC_F_SLOT_CELL, MKC_F_CELL_COUNT,
    MKC_F_MAG_FLAGS   /* provisional, failed, misfit, has_confirmed, confirmed b (3), F, first_accepted_at */
};
/* MKC_F_SLOT_AGE: the state keeps the slots' age order only (16-bit stamps); mkc_set takes ages (the
 * reference's samples seen when each slot was written) and stamps them 0 .. count-1 in their order,
 * mkc_get gives the stamps (smaller: older). */
/* Copy field `which` of a state (mkc_stream_t or mkc_mag_t, as `kind` 0/1) as doubles into out
 * (cap entries); returns the number of entries, or -1. Counts are converted to double. */
int mkc_get(const void *state, int kind, int which, double *out, int cap);
/* The inverse: write field `which` from n doubles (rounded to the field's type). Set MKC_F_CNT
 * first (window-sized fields use its count). Returns MKC_OK or MKC_BAD_INPUT. For tests that start
 * the port from a reference state (teacher forcing); the X/Y rows of a mkc_mag_t are not settable. */
int mkc_set(void *state, int kind, int which, const double *in, int n);
/* first_accepted_at, checkpoints, provisional, failed, pending, init_samples, policy, unit_ut,
 * misfit, has_confirmed into out[0..9]; returns 10. */
int mkc_mag_get_info(const mkc_mag_t *cal, int64_t *out, int cap);
/* Build facts: MKC_N, MKC_M, MKC_W, MKC_K, sizeof(mkc_real), sizeof(mkc_acc), sizeof(mkc_ereal),
 * sizeof(mkc_stream_t), sizeof(mkc_mag_t) into out[0..8]; returns 9. */
int mkc_build_info(long *out, int cap);

#ifdef __cplusplus
}
#endif

#endif /* MKC_INTROSPECT_H */
