/* Host commander: keeps the last accepted setpoint with its priority and tick. */
#include <string.h>

#include "commander.h"
#include "polycc_shim.h"
#include "sim_internal.h"

static shim_commander_record_t rec;
static setpoint_t last;

void shimCommanderReset(void)
{
    memset(&rec, 0, sizeof rec);
    memset(&last, 0, sizeof last);
    rec.active_priority = COMMANDER_PRIORITY_DISABLE;
}

void commanderInit(void)
{
    shimCommanderReset();
}

bool commanderTest(void)
{
    return true;
}

/* Same rule as the firmware: a setpoint replaces the current one when its priority is at
 * least the current one's. */
void commanderSetSetpoint(setpoint_t *setpoint, int priority)
{
    if (priority < rec.active_priority) {
        ++rec.rejected;
        return;
    }
    setpoint->timestamp = shim_get_tick();
    last = *setpoint;
    ++rec.count;
    rec.tick = setpoint->timestamp;
    rec.priority = priority;
    rec.active_priority = priority;
    rec.mode_x = (int)setpoint->mode.x;
    rec.mode_y = (int)setpoint->mode.y;
    rec.mode_z = (int)setpoint->mode.z;
    rec.mode_roll = (int)setpoint->mode.roll;
    rec.mode_pitch = (int)setpoint->mode.pitch;
    rec.mode_yaw = (int)setpoint->mode.yaw;
    rec.velocity_body = setpoint->velocity_body ? 1 : 0;
    rec.vx = setpoint->velocity.x;
    rec.vy = setpoint->velocity.y;
    rec.vz = setpoint->velocity.z;
    rec.yaw_rate = setpoint->attitudeRate.yaw;
}

int commanderGetActivePriority(void)
{
    return rec.active_priority;
}

void commanderRelaxPriority(void)
{
    ++rec.relax_count;
    rec.active_priority = COMMANDER_PRIORITY_LOWEST;
}

uint32_t commanderGetInactivityTime(void)
{
    return shim_get_tick() - rec.tick;
}

void commanderGetSetpoint(setpoint_t *setpoint, const state_t *state)
{
    (void)state;
    *setpoint = last;
}

void shim_commander_get(shim_commander_record_t *out)
{
    *out = rec;
}
