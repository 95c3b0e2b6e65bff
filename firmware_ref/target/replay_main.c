/* replay_main.c: replays a magnetometer stream through the calibrator and writes its state at every
 * checkpoint, on the emulated Cortex-M (semihost.c) or the host (stdio_io.c); the two outputs are
 * compared by tests/test_cortex_m.py.
 *
 * Input mkc_in.bin (replay_input.h: a header with the configuration and T, then T samples of 3
 * doubles), fed as mkc_real like mkc_replay does.
 * Output mkc_out.bin: one record of MKC_OUT_RECORD doubles per checkpoint (layout at the enum), then a
 * final record (samples_seen = -1) with the counts and the accepted calibration. Exit status 0, or
 * 1 for unreadable input, 2 for a configuration the library refuses.
 */
#include <stdint.h>

#include "mkc.h"
#include "mkc_target_io.h"
#include "replay_input.h"

/* record layout (doubles) */
enum {
    O_SEEN = 0, O_ESTEPS, O_STATUS, O_ACCEPTED, O_HAS_TRIAL, O_REASON, O_THETA, /* theta: 9 */
    O_SIGMA = O_THETA + 9, O_D, O_A, O_C0S0,                                   /* c0 (3), s0 */
    O_HARD = O_C0S0 + 4, O_SOFT = O_HARD + 3, O_FIELD = O_SOFT + 9, O_QUALITY,  /* quality: MKC_QUALITY */
    MKC_OUT_RECORD = O_QUALITY + MKC_QUALITY
};

static mkc_mag_t cal;             /* the state: static, never on the stack */

typedef struct sink {
    int handle;
    int failed;
} sink;

static void put_calibration(double *rec, const mkc_mag_calibration *c)
{
    int i, j;
    for (i = 0; i < 3; i++) {
        rec[O_HARD + i] = (double)c->hard_iron[i];
        for (j = 0; j < 3; j++)
            rec[O_SOFT + 3 * i + j] = (double)c->soft_iron[i][j];
    }
    rec[O_FIELD] = (double)c->field;
    for (i = 0; i < MKC_QUALITY; i++)
        rec[O_QUALITY + i] = (double)c->quality[i];
}

static void write_record(sink *out, const double *rec)
{
    if (mkc_io_write(out->handle, rec, MKC_OUT_RECORD * sizeof(double)) != (long)(MKC_OUT_RECORD * sizeof(double)))
        out->failed = 1;
}

static void on_checkpoint(void *user, const mkc_mag_t *g)
{
    const mkc_mag_event *ev = &g->last_event;
    double rec[MKC_OUT_RECORD] = {0.0};
    int j;
    rec[O_SEEN] = (double)ev->samples_seen;
    rec[O_ESTEPS] = (double)g->core.counters.esteps;
    rec[O_STATUS] = (double)g->core.counters.status;
    rec[O_ACCEPTED] = ev->accepted ? 1.0 : 0.0;
    rec[O_HAS_TRIAL] = ev->has_calibration ? 1.0 : 0.0;
    rec[O_REASON] = (double)ev->reason.code;
    for (j = 0; j < 9; j++)
        rec[O_THETA + j] = (double)g->core.theta[j];
    rec[O_SIGMA] = (double)g->core.sigma[0];
    rec[O_D] = (double)g->core.d[0];
    rec[O_A] = (double)g->core.a[0];
    for (j = 0; j < 3; j++)
        rec[O_C0S0 + j] = (double)g->c0[j];
    rec[O_C0S0 + 3] = (double)g->s0;
    if (ev->has_calibration)
        put_calibration(rec, &g->trial);
    write_record((sink *)user, rec);
}

int main(void)
{
    double block[3 * MKC_IN_BLOCK], rec[MKC_OUT_RECORD] = {0.0};
    mkc_mag_config cfg;
    const mkc_mag_calibration *acc;
    int64_t samples, bad_frames;
    int32_t T, done = 0;
    sink out = {-1, 0};
    int in = mkc_replay_open_input(&cfg, &T);
    if (in < 0)
        return 1;
    if (mkc_mag_init(&cal, &cfg) != MKC_OK) {
        mkc_io_console("mkc target replay: the library refuses the configuration\n");
        return 2;
    }
    out.handle = mkc_io_open("mkc_out.bin", 1);
    if (out.handle < 0) {
        mkc_io_console("mkc target replay: cannot write mkc_out.bin\n");
        return 1;
    }
    mkc_mag_set_listener(&cal, on_checkpoint, &out);
    while (done < T) {
        int32_t n = T - done < MKC_IN_BLOCK ? T - done : MKC_IN_BLOCK, k;
        if (mkc_replay_read_block(in, block, n) != 0)
            return 1;
        for (k = 0; k < n; k++)
            mkc_mag_push(&cal, (mkc_real)block[3 * k], (mkc_real)block[3 * k + 1], (mkc_real)block[3 * k + 2]);
        done += n;
    }
    mkc_io_close(in);
    mkc_mag_counts(&cal, &samples, &bad_frames);
    acc = mkc_mag_get_calibration(&cal, 1);
    rec[O_SEEN] = -1.0;
    rec[O_ESTEPS] = (double)cal.core.counters.esteps;
    rec[O_STATUS] = (double)samples;
    rec[O_ACCEPTED] = acc ? 1.0 : 0.0;
    rec[O_HAS_TRIAL] = (double)bad_frames;
    if (acc)
        put_calibration(rec, acc);
    write_record(&out, rec);
    mkc_io_close(out.handle);
    mkc_io_console(out.failed ? "mkc target replay: write error\n" : "mkc target replay: done\n");
    return out.failed ? 1 : 0;
}
