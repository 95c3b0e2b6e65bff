/* mkc_target_io.h: the replay harness's file I/O, implemented twice: by Arm semihosting on the
 * emulated board (semihost.c) and by stdio on the host (stdio_io.c), so one harness source gives
 * the target's and the host's output for the same input. */
#ifndef MKC_TARGET_IO_H
#define MKC_TARGET_IO_H

#include <stddef.h>

/* Open a file for binary reading (write = 0) or writing (write = 1); returns a handle >= 0, or -1. */
int mkc_io_open(const char *path, int write);
/* Bytes transferred (fewer than n at the end of the file), or -1 on an error. */
long mkc_io_read(int handle, void *buf, size_t n);
long mkc_io_write(int handle, const void *buf, size_t n);
void mkc_io_close(int handle);
/* A line of text on the console (stderr on the host). */
void mkc_io_console(const char *text);

#endif /* MKC_TARGET_IO_H */
