/* semihost.c: the harness's file I/O on the emulated board by Arm semihosting (see mkc_target_io.h):
 * "bkpt 0xAB" with the operation in r0 and its parameter block in r1; the debugger (qemu-system-arm
 * -semihosting) performs it on the host and returns the result in r0. */
#include <stdint.h>

#include "mkc_target_io.h"

enum { SYS_OPEN = 0x01, SYS_CLOSE = 0x02, SYS_WRITE0 = 0x04, SYS_WRITE = 0x05, SYS_READ = 0x06, SYS_EXIT = 0x18 };
enum { MODE_RB = 1, MODE_WB = 5 };            /* fopen modes "rb", "wb" */
enum { ADP_STOPPED_APPLICATION_EXIT = 0x20026, ADP_STOPPED_RUN_TIME_ERROR = 0x20023 };

static int32_t semihost(int32_t op, const void *params)
{
    register int32_t r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = params;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

static uint32_t length(const char *s)
{
    uint32_t n = 0;
    while (s[n])
        n++;
    return n;
}

int mkc_io_open(const char *path, int write)
{
    uint32_t p[3];
    p[0] = (uint32_t)(uintptr_t)path;
    p[1] = write ? MODE_WB : MODE_RB;
    p[2] = length(path);
    return (int)semihost(SYS_OPEN, p);
}

/* SYS_READ and SYS_WRITE return the bytes NOT transferred. */
long mkc_io_read(int handle, void *buf, size_t n)
{
    uint32_t p[3];
    int32_t left;
    p[0] = (uint32_t)handle;
    p[1] = (uint32_t)(uintptr_t)buf;
    p[2] = (uint32_t)n;
    left = semihost(SYS_READ, p);
    return left < 0 ? -1 : (long)n - (long)left;
}

long mkc_io_write(int handle, const void *buf, size_t n)
{
    uint32_t p[3];
    p[0] = (uint32_t)handle;
    p[1] = (uint32_t)(uintptr_t)buf;
    p[2] = (uint32_t)n;
    return semihost(SYS_WRITE, p) == 0 ? (long)n : -1;
}

void mkc_io_close(int handle)
{
    uint32_t p[1];
    p[0] = (uint32_t)handle;
    (void)semihost(SYS_CLOSE, p);
}

void mkc_io_console(const char *text)
{
    (void)semihost(SYS_WRITE0, text);
}

/* Ends the emulation: qemu exits with status 0 for an application exit, 1 otherwise. */
void mkc_target_exit(int status)
{
    (void)semihost(SYS_EXIT, (const void *)(uintptr_t)(status == 0 ? ADP_STOPPED_APPLICATION_EXIT
                                                                   : ADP_STOPPED_RUN_TIME_ERROR));
    for (;;) {
    }
}
