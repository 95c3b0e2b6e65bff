/* replay_input.h: the harnesses' input file mkc_in.bin (little-endian): 8 int32 (MKC_IN_MAGIC,
 * MKC_IO_VERSION, window, estep_every, policy (MKC_POLICY_*), unit_ut, init_samples, T), then T samples
 * of 3 doubles (mx, my, mz), read in blocks so the stream need not fit the board's memory. Shared by
 * the replay harness (replay_main.c) and the measuring harness (measure_main.c). */
#ifndef MKC_REPLAY_INPUT_H
#define MKC_REPLAY_INPUT_H

#include <stdint.h>

#include "mkc.h"

#define MKC_IN_MAGIC 0x49434B4D   /* "MKCI" */
#define MKC_IO_VERSION 1
#define MKC_IN_BLOCK 64           /* samples per read */

/* Opens mkc_in.bin and reads its header into cfg (from mkc_mag_config_default) and *T.
 * Returns the open handle, or -1 (message on the console) when the file is missing or not a
 * version-1 input. */
int mkc_replay_open_input(mkc_mag_config *cfg, int32_t *T);
/* Reads the next n (<= MKC_IN_BLOCK) samples into block (3 n doubles); 0, or -1 (message on the
 * console) when the file is shorter than its header says. */
int mkc_replay_read_block(int in, double *block, int32_t n);

#endif /* MKC_REPLAY_INPUT_H */
