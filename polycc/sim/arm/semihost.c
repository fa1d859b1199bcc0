#include "semihost.h"

#include <string.h>

static int semihost_call(int op, void *arg)
{
    register int r0 __asm__("r0") = op;
    register void *r1 __asm__("r1") = arg;
    __asm volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

int semihost_open(const char *path, int mode)
{
    uintptr_t a[3] = {(uintptr_t)path, (uintptr_t)mode, (uintptr_t)strlen(path)};
    return semihost_call(0x01, a);
}

int semihost_read(int fd, void *buf, size_t n)
{
    uintptr_t a[3] = {(uintptr_t)fd, (uintptr_t)buf, (uintptr_t)n};
    return (int)n - semihost_call(0x06, a);
}

int semihost_write(int fd, const void *buf, size_t n)
{
    uintptr_t a[3] = {(uintptr_t)fd, (uintptr_t)buf, (uintptr_t)n};
    return semihost_call(0x05, a);
}

void semihost_close(int fd)
{
    uintptr_t a[1] = {(uintptr_t)fd};
    (void)semihost_call(0x02, a);
}

void semihost_puts(const char *s)
{
    (void)semihost_call(0x04, (void *)s);
}

void semihost_exit(int code)
{
    /* SYS_EXIT_EXTENDED: {ADP_Stopped_ApplicationExit, exit code}. */
    uintptr_t a[2] = {0x20026u, (uintptr_t)code};
    (void)semihost_call(0x20, a);
    for (;;) {
    }
}

int semihost_read_all(int fd, void *buf, size_t n)
{
    return semihost_read(fd, buf, n) == (int)n;
}

int semihost_slurp(const char *path, void *buf, size_t cap)
{
    int got, fd = semihost_open(path, 1);
    if (fd < 0) {
        return -1;
    }
    got = semihost_read(fd, buf, cap);
    semihost_close(fd);
    return got;
}
