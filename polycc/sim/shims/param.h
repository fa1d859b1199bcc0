/* Shim of crazyflie-firmware src/modules/interface/param.h: the parameter table entry, type
 * bits and the PARAM_GROUP_START / PARAM_ADD / PARAM_GROUP_STOP macros.
 *
 * With POLYCC_SHIM_HOST defined, PARAM_GROUP_STOP also emits a constructor that registers
 * the table with the host param TOC (sim_param.c, enumerable through polycc_shim.h). */
#pragma once

#include <stdint.h>

struct param_s {
    uint8_t type;
    uint8_t extended_type;
    char *name;
    void *address;
    void (*callback)(void);
    void *(*getter)(void);
};

#define PARAM_BYTES_MASK 0x03
#define PARAM_1BYTE 0x00
#define PARAM_2BYTES 0x01
#define PARAM_4BYTES 0x02
#define PARAM_8BYTES 0x03

#define PARAM_TYPE_MASK 0x0F
#define PARAM_TYPE_INT (0x00 << 2)
#define PARAM_TYPE_FLOAT (0x01 << 2)

#define PARAM_SIGNED (0x00 << 3)
#define PARAM_UNSIGNED (0x01 << 3)

#define PARAM_VARIABLE (0x00 << 7)
#define PARAM_GROUP (0x01 << 7)

#define PARAM_EXTENDED (1 << 4)
#define PARAM_CORE (1 << 5)
#define PARAM_RONLY (1 << 6)

#define PARAM_START 1
#define PARAM_STOP 0

#define PARAM_PERSISTENT (1 << 8)

#define PARAM_UINT8 (PARAM_1BYTE | PARAM_TYPE_INT | PARAM_UNSIGNED)
#define PARAM_INT8 (PARAM_1BYTE | PARAM_TYPE_INT | PARAM_SIGNED)
#define PARAM_UINT16 (PARAM_2BYTES | PARAM_TYPE_INT | PARAM_UNSIGNED)
#define PARAM_INT16 (PARAM_2BYTES | PARAM_TYPE_INT | PARAM_SIGNED)
#define PARAM_UINT32 (PARAM_4BYTES | PARAM_TYPE_INT | PARAM_UNSIGNED)
#define PARAM_INT32 (PARAM_4BYTES | PARAM_TYPE_INT | PARAM_SIGNED)
#define PARAM_FLOAT (PARAM_4BYTES | PARAM_TYPE_FLOAT | PARAM_SIGNED)

#define PARAM_ADD_FULL(TYPE, NAME, ADDRESS, CALLBACK, DEFAULT_GETTER)                              \
    {.type = ((TYPE) <= 0xFF) ? ((TYPE) & 0xFF) : (((TYPE) | PARAM_EXTENDED) & 0xFF),              \
     .extended_type = (((TYPE) & 0xFF00) >> 8),                                                   \
     .name = #NAME,                                                                               \
     .address = (void *)(ADDRESS),                                                                \
     .callback = (void (*)(void))CALLBACK,                                                        \
     .getter = (void *(*)(void))DEFAULT_GETTER},
#define PARAM_ADD(TYPE, NAME, ADDRESS) PARAM_ADD_FULL(TYPE, NAME, ADDRESS, 0, 0)
#define PARAM_ADD_WITH_CALLBACK(TYPE, NAME, ADDRESS, CALLBACK) PARAM_ADD_FULL(TYPE, NAME, ADDRESS, CALLBACK, 0)
#define PARAM_ADD_CORE(TYPE, NAME, ADDRESS) PARAM_ADD((TYPE) | PARAM_CORE, NAME, ADDRESS)
#define PARAM_ADD_CORE_WITH_CALLBACK(TYPE, NAME, ADDRESS, CALLBACK) \
    PARAM_ADD_WITH_CALLBACK((TYPE) | PARAM_CORE, NAME, ADDRESS, CALLBACK)
#define PARAM_ADD_GROUP(TYPE, NAME, ADDRESS) \
    {.type = (TYPE), .name = #NAME, .address = (void *)(ADDRESS), .callback = 0, .getter = 0},

#ifdef POLYCC_SHIM_HOST
void shimParamRegisterGroup(const struct param_s *table);
#define PARAM_GROUP_START(NAME)               \
    static struct param_s __params_##NAME[] = { \
        PARAM_ADD_GROUP(PARAM_GROUP | PARAM_START, NAME, 0x0)
#define PARAM_GROUP_STOP(NAME)                                             \
    PARAM_ADD_GROUP(PARAM_GROUP | PARAM_STOP, stop_##NAME, 0x0)            \
    };                                                                     \
    __attribute__((constructor)) static void shimParamRegister_##NAME(void) \
    {                                                                      \
        shimParamRegisterGroup(__params_##NAME);                           \
    }
#else
#define PARAM_GROUP_START(NAME)                                                             \
    static struct param_s __params_##NAME[] __attribute__((section(".param." #NAME), used)) = { \
        PARAM_ADD_GROUP(PARAM_GROUP | PARAM_START, NAME, 0x0)
#define PARAM_GROUP_STOP(NAME)                                  \
    PARAM_ADD_GROUP(PARAM_GROUP | PARAM_STOP, stop_##NAME, 0x0) \
    };
#endif

/* param_logic.h (included by the firmware's param.h): look-up of a parameter by name, for apps. */
typedef struct paramVarId_s {
    uint16_t id;
    uint16_t index;
} __attribute__((packed)) paramVarId_t;
#define PARAM_VARID_IS_VALID(varId) ((varId).id != 0xffffu)
paramVarId_t paramGetVarId(const char *group, const char *name);
float paramGetFloat(paramVarId_t varid);
