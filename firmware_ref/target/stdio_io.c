/* stdio_io.c: the harness's file I/O on the host (see mkc_target_io.h). */
#include <stdio.h>

#include "mkc_target_io.h"

#define MAX_FILES 4

static FILE *files[MAX_FILES];

int mkc_io_open(const char *path, int write)
{
    int h;
    for (h = 0; h < MAX_FILES; h++) {
        if (!files[h]) {
            files[h] = fopen(path, write ? "wb" : "rb");
            return files[h] ? h : -1;
        }
    }
    return -1;
}

long mkc_io_read(int handle, void *buf, size_t n)
{
    size_t got = fread(buf, 1, n, files[handle]);
    return ferror(files[handle]) ? -1 : (long)got;
}

long mkc_io_write(int handle, const void *buf, size_t n)
{
    return fwrite(buf, 1, n, files[handle]) == n ? (long)n : -1;
}

void mkc_io_close(int handle)
{
    fclose(files[handle]);
    files[handle] = NULL;
}

void mkc_io_console(const char *text)
{
    fputs(text, stderr);
}
