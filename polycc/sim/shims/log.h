/* Shim of crazyflie-firmware src/modules/interface/log.h: the public log API, the log
 * table entry and the LOG_GROUP_START / LOG_ADD / LOG_GROUP_STOP macros.
 *
 * With POLYCC_SHIM_HOST defined, LOG_GROUP_STOP also emits a constructor that registers
 * the table with the host log TOC (sim_log.c, enumerable through polycc_shim.h). */
#pragma once

#include <stdbool.h>
#include <stdint.h>

typedef uint16_t logVarId_t;

logVarId_t logGetVarId(const char *group, const char *name);
static inline bool logVarIdIsValid(logVarId_t varId)
{
    return varId != 0xffffu;
}
int logGetType(logVarId_t varid);
void logGetGroupAndName(logVarId_t varid, char **group, char **name);
void *logGetAddress(logVarId_t varid);
uint8_t logVarSize(int type);
float logGetFloat(logVarId_t varid);
int logGetInt(logVarId_t varid);
unsigned int logGetUint(logVarId_t varid);

struct log_s {
    uint8_t type;
    char *name;
    void *address;
};

#define LOG_UINT8 1
#define LOG_UINT16 2
#define LOG_UINT32 3
#define LOG_INT8 4
#define LOG_INT16 5
#define LOG_INT32 6
#define LOG_FLOAT 7
#define LOG_FP16 8

#define LOG_CORE 0x20
#define LOG_GROUP 0x80
#define LOG_BY_FUNCTION 0x40
#define LOG_START 1
#define LOG_STOP 0

#define LOG_ADD(TYPE, NAME, ADDRESS) {.type = (TYPE), .name = #NAME, .address = (void *)(ADDRESS)},
#define LOG_ADD_CORE(TYPE, NAME, ADDRESS) LOG_ADD((TYPE) | LOG_CORE, NAME, ADDRESS)
#define LOG_ADD_BY_FUNCTION(TYPE, NAME, ADDRESS) LOG_ADD((TYPE) | LOG_BY_FUNCTION, NAME, ADDRESS)
#define LOG_ADD_GROUP(TYPE, NAME, ADDRESS) LOG_ADD(TYPE, NAME, ADDRESS)
#define LOG_ADD_DEBUG(TYPE, NAME, ADDRESS) LOG_ADD(TYPE, NAME, ADDRESS)

#ifdef POLYCC_SHIM_HOST
void shimLogRegisterGroup(const struct log_s *table);
#define LOG_GROUP_START(NAME)                        \
    static const struct log_s __logs_##NAME[] = { \
        LOG_ADD_GROUP(LOG_GROUP | LOG_START, NAME, 0x0)
#define LOG_GROUP_STOP(NAME)                                                        \
    LOG_ADD_GROUP(LOG_GROUP | LOG_STOP, stop_##NAME, 0x0)                           \
    };                                                                              \
    __attribute__((constructor)) static void shimLogRegister_##NAME(void)          \
    {                                                                               \
        shimLogRegisterGroup(__logs_##NAME);                                        \
    }
#else
#define LOG_GROUP_START(NAME)                                                                   \
    static const struct log_s __logs_##NAME[] __attribute__((section(".log." #NAME), used)) = { \
        LOG_ADD_GROUP(LOG_GROUP | LOG_START, NAME, 0x0)
#define LOG_GROUP_STOP(NAME)                              \
    LOG_ADD_GROUP(LOG_GROUP | LOG_STOP, stop_##NAME, 0x0) \
    };
#endif
