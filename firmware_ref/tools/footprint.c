/* footprint: sizeof the states for the configuration this file is compiled with (make footprint
 * compiles it for each row of the README table). One line: precision n m W stream_bytes mag_bytes
 * core_bytes window_part. */
#include <stdio.h>

#include "mkc.h"

int main(int argc, char **argv)
{
    const char *prec = argc > 1 ? argv[1] : (sizeof(mkc_real) == 8 ? "double" : "float");
    printf("%-11s n=%-2d m=%d W=%-5d  mkc_stream_t %7lu B", prec, MKC_N, MKC_M, MKC_W,
           (unsigned long)sizeof(mkc_stream_t));
    if (MKC_N == 9 && MKC_M == 1)       /* the magnetometer state is meant for n = 9, m = 1 */
        printf("   mkc_mag_t %7lu B (%.2f KiB; its cold-start copy, in the weights' bytes, %lu B)", (unsigned long)sizeof(mkc_mag_t),
               (double)sizeof(mkc_mag_t) / 1024.0, (unsigned long)MKC_CORE_SAVED_BYTES);
    printf("\n");
    return 0;
}
