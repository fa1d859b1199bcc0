/* Host parameter TOC: registry of PARAM_GROUP tables, read and write by index. */
#include <math.h>
#include <string.h>

#include "param.h"
#include "polycc_shim.h"

#define SHIM_MAX_GROUPS 64
#define SHIM_MAX_PARAMS 1024

typedef struct {
    const char *group;
    struct param_s *entry;
} shim_param_var_t;

static struct param_s *groups[SHIM_MAX_GROUPS];
static int nGroups;
static shim_param_var_t vars[SHIM_MAX_PARAMS];
static int nVars;

static int isStop(const struct param_s *e)
{
    return (e->type & PARAM_GROUP) && (e->type & PARAM_START) == 0;
}

static void rebuild(void)
{
    int g;
    nVars = 0;
    for (g = 0; g < nGroups; ++g) {
        struct param_s *e = groups[g] + 1;
        for (; !isStop(e) && nVars < SHIM_MAX_PARAMS; ++e) {
            vars[nVars].group = groups[g]->name;
            vars[nVars].entry = e;
            ++nVars;
        }
    }
}

void shimParamRegisterGroup(const struct param_s *table)
{
    int i;
    if (nGroups >= SHIM_MAX_GROUPS) {
        return;
    }
    i = nGroups++;
    while (i > 0 && strcmp(groups[i - 1]->name, table->name) > 0) {
        groups[i] = groups[i - 1];
        --i;
    }
    groups[i] = (struct param_s *)table;
    rebuild();
}

int shim_param_count(void)
{
    return nVars;
}

int shim_param_entry(int index, shim_toc_entry_t *out)
{
    if (index < 0 || index >= nVars) {
        return -1;
    }
    out->group = vars[index].group;
    out->name = vars[index].entry->name;
    out->type = vars[index].entry->type;
    out->extended_type = vars[index].entry->extended_type;
    out->address = vars[index].entry->address;
    out->callback = vars[index].entry->callback;
    return 0;
}

int shim_param_index(const char *group, const char *name)
{
    int i;
    for (i = 0; i < nVars; ++i) {
        if (strcmp(vars[i].group, group) == 0 && strcmp(vars[i].entry->name, name) == 0) {
            return i;
        }
    }
    return -1;
}

int shim_param_type_size(uint8_t type)
{
    return 1 << (type & PARAM_BYTES_MASK);
}

double shim_param_value(int index)
{
    const struct param_s *e;
    const void *a;
    if (index < 0 || index >= nVars) {
        return (double)NAN;
    }
    e = vars[index].entry;
    a = e->address;
    if (e->type & PARAM_TYPE_FLOAT) {
        return (e->type & PARAM_BYTES_MASK) == PARAM_8BYTES ? *(const double *)a : (double)*(const float *)a;
    }
    switch (e->type & (PARAM_BYTES_MASK | PARAM_UNSIGNED)) {
    case PARAM_1BYTE | PARAM_UNSIGNED: return *(const uint8_t *)a;
    case PARAM_1BYTE: return *(const int8_t *)a;
    case PARAM_2BYTES | PARAM_UNSIGNED: return *(const uint16_t *)a;
    case PARAM_2BYTES: return *(const int16_t *)a;
    case PARAM_4BYTES | PARAM_UNSIGNED: return *(const uint32_t *)a;
    case PARAM_4BYTES: return *(const int32_t *)a;
    case PARAM_8BYTES | PARAM_UNSIGNED: return (double)*(const uint64_t *)a;
    default: return (double)*(const int64_t *)a;
    }
}

static double clampd(double v, double lo, double hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

int shim_param_set(int index, double value)
{
    struct param_s *e;
    void *a;
    if (index < 0 || index >= nVars) {
        return -1;
    }
    e = vars[index].entry;
    if (e->type & PARAM_RONLY) {
        return -2;
    }
    a = e->address;
    if (e->type & PARAM_TYPE_FLOAT) {
        if ((e->type & PARAM_BYTES_MASK) == PARAM_8BYTES) {
            *(double *)a = value;
        } else {
            *(float *)a = (float)value;
        }
    } else {
        double v = isnan(value) ? 0.0 : trunc(value);
        switch (e->type & (PARAM_BYTES_MASK | PARAM_UNSIGNED)) {
        case PARAM_1BYTE | PARAM_UNSIGNED: *(uint8_t *)a = (uint8_t)clampd(v, 0.0, 255.0); break;
        case PARAM_1BYTE: *(int8_t *)a = (int8_t)clampd(v, -128.0, 127.0); break;
        case PARAM_2BYTES | PARAM_UNSIGNED: *(uint16_t *)a = (uint16_t)clampd(v, 0.0, 65535.0); break;
        case PARAM_2BYTES: *(int16_t *)a = (int16_t)clampd(v, -32768.0, 32767.0); break;
        case PARAM_4BYTES | PARAM_UNSIGNED: *(uint32_t *)a = (uint32_t)clampd(v, 0.0, 4294967295.0); break;
        case PARAM_4BYTES: *(int32_t *)a = (int32_t)clampd(v, -2147483648.0, 2147483647.0); break;
        case PARAM_8BYTES | PARAM_UNSIGNED: *(uint64_t *)a = (uint64_t)clampd(v, 0.0, 1.8446744073709550e19); break;
        default: *(int64_t *)a = (int64_t)clampd(v, -9.2233720368547758e18, 9.2233720368547748e18); break;
        }
    }
    if (e->callback) {
        e->callback();
    }
    return 0;
}

paramVarId_t paramGetVarId(const char *group, const char *name)
{
    paramVarId_t id;
    int i = shim_param_index(group, name);
    id.id = i < 0 ? 0xffffu : (uint16_t)i;
    id.index = id.id;
    return id;
}

float paramGetFloat(paramVarId_t varid)
{
    return varid.id == 0xffffu ? 0.0f : (float)shim_param_value((int)varid.id);
}
