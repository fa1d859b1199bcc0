/* Host log TOC: registry of LOG_GROUP tables, the log API, and the simulated estimate. */
#include <math.h>
#include <string.h>

#include "log.h"
#include "polycc_shim.h"
#include "sim_internal.h"

#define SHIM_MAX_GROUPS 64
#define SHIM_MAX_VARS 1024

typedef struct {
    const char *group;
    const struct log_s *entry;
} shim_log_var_t;

static const struct log_s *groups[SHIM_MAX_GROUPS];
static int nGroups;
static shim_log_var_t vars[SHIM_MAX_VARS];
static int nVars;
static int kalmanPresent = 1, estimatePresent = 1;

static float estX, estY, estZ, estVx, estVy, estVz, estRoll, estPitch, estYaw;
static float varX = 1e-4f, varY = 1e-4f, varZ = 1e-4f;

LOG_GROUP_START(stateEstimate)
LOG_ADD_CORE(LOG_FLOAT, x, &estX)
LOG_ADD_CORE(LOG_FLOAT, y, &estY)
LOG_ADD_CORE(LOG_FLOAT, z, &estZ)
LOG_ADD_CORE(LOG_FLOAT, vx, &estVx)
LOG_ADD_CORE(LOG_FLOAT, vy, &estVy)
LOG_ADD_CORE(LOG_FLOAT, vz, &estVz)
LOG_ADD_CORE(LOG_FLOAT, roll, &estRoll)
LOG_ADD_CORE(LOG_FLOAT, pitch, &estPitch)
LOG_ADD_CORE(LOG_FLOAT, yaw, &estYaw)
LOG_GROUP_STOP(stateEstimate)

void shimLogSetYaw(float roll_deg, float pitch_deg, float yaw_deg)
{
    estRoll = roll_deg;
    estPitch = pitch_deg;
    estYaw = yaw_deg;
}

LOG_GROUP_START(kalman)
LOG_ADD(LOG_FLOAT, varX, &varX)
LOG_ADD(LOG_FLOAT, varY, &varY)
LOG_ADD(LOG_FLOAT, varZ, &varZ)
LOG_GROUP_STOP(kalman)

static int isStop(const struct log_s *e)
{
    return (e->type & LOG_GROUP) && (e->type & LOG_START) == 0;
}

static void rebuild(void)
{
    int g;
    nVars = 0;
    for (g = 0; g < nGroups; ++g) {
        const struct log_s *e = groups[g] + 1;
        for (; !isStop(e) && nVars < SHIM_MAX_VARS; ++e) {
            vars[nVars].group = groups[g]->name;
            vars[nVars].entry = e;
            ++nVars;
        }
    }
}

void shimLogRegisterGroup(const struct log_s *table)
{
    int i;
    if (nGroups >= SHIM_MAX_GROUPS) {
        return;
    }
    i = nGroups++;
    while (i > 0 && strcmp(groups[i - 1]->name, table->name) > 0) { /* keep sorted by name */
        groups[i] = groups[i - 1];
        --i;
    }
    groups[i] = table;
    rebuild();
}

static int hidden(int id)
{
    const char *g = vars[id].group;
    return (!kalmanPresent && strcmp(g, "kalman") == 0) || (!estimatePresent && strcmp(g, "stateEstimate") == 0);
}

logVarId_t logGetVarId(const char *group, const char *name)
{
    int i;
    for (i = 0; i < nVars; ++i) {
        if (strcmp(vars[i].group, group) == 0 && strcmp(vars[i].entry->name, name) == 0) {
            return hidden(i) ? (logVarId_t)0xffffu : (logVarId_t)i;
        }
    }
    return (logVarId_t)0xffffu;
}

static int valid(logVarId_t id)
{
    return id < nVars;
}

int logGetType(logVarId_t varid)
{
    return valid(varid) ? (vars[varid].entry->type & 0x0f) : 0;
}

void logGetGroupAndName(logVarId_t varid, char **group, char **name)
{
    *group = valid(varid) ? (char *)vars[varid].group : 0;
    *name = valid(varid) ? vars[varid].entry->name : 0;
}

void *logGetAddress(logVarId_t varid)
{
    return valid(varid) ? vars[varid].entry->address : 0;
}

uint8_t logVarSize(int type)
{
    return (uint8_t)shim_log_type_size((uint8_t)type);
}

int shim_log_type_size(uint8_t type)
{
    switch (type & 0x0f) {
    case LOG_UINT8:
    case LOG_INT8:
        return 1;
    case LOG_UINT16:
    case LOG_INT16:
    case LOG_FP16:
        return 2;
    case LOG_UINT32:
    case LOG_INT32:
    case LOG_FLOAT:
        return 4;
    default:
        return 0;
    }
}

static double valueOf(const struct log_s *e)
{
    const void *a = e->address;
    switch (e->type & 0x0f) {
    case LOG_UINT8: return *(const uint8_t *)a;
    case LOG_INT8: return *(const int8_t *)a;
    case LOG_UINT16: return *(const uint16_t *)a;
    case LOG_INT16: return *(const int16_t *)a;
    case LOG_UINT32: return *(const uint32_t *)a;
    case LOG_INT32: return *(const int32_t *)a;
    case LOG_FLOAT: return (double)*(const float *)a;
    default: return (double)NAN;
    }
}

float logGetFloat(logVarId_t varid)
{
    if (!valid(varid)) {
        return 0.0f;
    }
    if ((vars[varid].entry->type & 0x0f) == LOG_FLOAT) {
        return *(const float *)vars[varid].entry->address;
    }
    return (float)valueOf(vars[varid].entry);
}

int logGetInt(logVarId_t varid)
{
    return valid(varid) ? (int)valueOf(vars[varid].entry) : 0;
}

unsigned int logGetUint(logVarId_t varid)
{
    return valid(varid) ? (unsigned int)valueOf(vars[varid].entry) : 0u;
}

int shim_log_count(void)
{
    return nVars;
}

int shim_log_entry(int index, shim_toc_entry_t *out)
{
    if (index < 0 || index >= nVars) {
        return -1;
    }
    out->group = vars[index].group;
    out->name = vars[index].entry->name;
    out->type = vars[index].entry->type;
    out->extended_type = 0;
    out->address = vars[index].entry->address;
    out->callback = 0;
    return 0;
}

double shim_log_value(int index)
{
    return (index < 0 || index >= nVars) ? (double)NAN : valueOf(vars[index].entry);
}

void shim_set_estimate(float x, float y, float z, float vx, float vy, float vz)
{
    estX = x;
    estY = y;
    estZ = z;
    estVx = vx;
    estVy = vy;
    estVz = vz;
}

void shim_set_position_variance(float var_x, float var_y, float var_z)
{
    varX = var_x;
    varY = var_y;
    varZ = var_z;
}

void shim_set_kalman_present(int present)
{
    kalmanPresent = present != 0;
}

void shim_set_estimate_present(int present)
{
    estimatePresent = present != 0;
}

void shimLogReset(void)
{
    kalmanPresent = 1;
    estimatePresent = 1;
    shim_set_estimate(0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f);
    shim_set_position_variance(1e-4f, 1e-4f, 1e-4f);
}
