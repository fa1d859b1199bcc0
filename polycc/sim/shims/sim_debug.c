/* Host DEBUG_PRINT: formats into a buffer that Python reads with shim_debug_read. */
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "debug.h"
#include "polycc_shim.h"
#include "sim_internal.h"

#define SHIM_DEBUG_BYTES 8192

static char buf[SHIM_DEBUG_BYTES];
static size_t used;

void shimDebugReset(void)
{
    used = 0u;
    buf[0] = '\0';
}

int shimDebugPrintf(const char *fmt, ...)
{
    va_list ap;
    int n;
    va_start(ap, fmt);
    n = vsnprintf(buf + used, sizeof buf - used, fmt, ap);
    va_end(ap);
    if (n > 0) {
        used += (size_t)n < sizeof buf - used ? (size_t)n : sizeof buf - used - 1u;
    }
    return n;
}

size_t shim_debug_read(char *out, size_t n)
{
    size_t k = used < n - 1u ? used : n - 1u;
    memcpy(out, buf, k);
    out[k] = '\0';
    used = 0u;
    buf[0] = '\0';
    return k;
}
