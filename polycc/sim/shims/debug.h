/* Shim of crazyflie-firmware src/utils/interface/debug.h: DEBUG_PRINT with the module prefix. */
#pragma once

#ifndef DEBUG_MODULE
#define DEBUG_MODULE ""
#endif

int shimDebugPrintf(const char *fmt, ...) __attribute__((format(printf, 1, 2)));

#define DEBUG_FMT(fmt) DEBUG_MODULE ": " fmt
#define DEBUG_PRINT(fmt, ...) shimDebugPrintf(DEBUG_FMT(fmt), ##__VA_ARGS__)
#define DEBUG_PRINT_OS(fmt, ...) shimDebugPrintf(DEBUG_FMT(fmt), ##__VA_ARGS__)
