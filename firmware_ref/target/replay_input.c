/* replay_input.c: reads the harnesses' input file mkc_in.bin (format in replay_input.h). */
#include "replay_input.h"
#include "mkc_target_io.h"

static int32_t le32(const unsigned char *p)
{
    return (int32_t)((uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24);
}

int mkc_replay_open_input(mkc_mag_config *cfg, int32_t *T)
{
    unsigned char head[32];
    int in = mkc_io_open("mkc_in.bin", 0);
    if (in < 0 || mkc_io_read(in, head, sizeof head) != (long)sizeof head || le32(head) != MKC_IN_MAGIC
        || le32(head + 4) != MKC_IO_VERSION) {
        mkc_io_console("mkc target replay: cannot read mkc_in.bin (or not a version-1 input)\n");
        return -1;
    }
    mkc_mag_config_default(cfg);
    cfg->stream.window = le32(head + 8);
    cfg->stream.estep_every = le32(head + 12);
    cfg->policy = le32(head + 16);
    cfg->unit_ut = le32(head + 20);
    cfg->init_samples = le32(head + 24);
    *T = le32(head + 28);
    return in;
}

int mkc_replay_read_block(int in, double *block, int32_t n)
{
    if (mkc_io_read(in, block, (size_t)n * 3 * sizeof(double)) != (long)((size_t)n * 3 * sizeof(double))) {
        mkc_io_console("mkc target replay: mkc_in.bin is shorter than its header says\n");
        return -1;
    }
    return 0;
}
