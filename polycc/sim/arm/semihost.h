/* ARM semihosting (bkpt 0xab) calls used by the bare-metal test and benchmark programs. */
#ifndef POLYCC_SEMIHOST_H
#define POLYCC_SEMIHOST_H
#include <stddef.h>
#include <stdint.h>

int semihost_open(const char *path, int mode); /* mode 1 = "rb", 5 = "wb" */
int semihost_read(int fd, void *buf, size_t n); /* returns bytes read */
int semihost_write(int fd, const void *buf, size_t n); /* returns 0 on success */
void semihost_close(int fd);
void semihost_puts(const char *s);
void semihost_exit(int code);
int semihost_read_all(int fd, void *buf, size_t n); /* 1 if exactly n bytes were read */
int semihost_slurp(const char *path, void *buf, size_t cap); /* a whole file (<= cap bytes): its size, or -1 */
#endif
