/* Shim of crazyflie-firmware src/modules/interface/commander.h. */
#pragma once

#include <stdbool.h>
#include <stdint.h>

#include "stabilizer_types.h"

#define COMMANDER_PRIORITY_DISABLE 0
#define COMMANDER_PRIORITY_LOWEST 1
#define COMMANDER_PRIORITY_HIGHLEVEL 1
#define COMMANDER_PRIORITY_CRTP 2
#define COMMANDER_PRIORITY_EXTRX 3

void commanderInit(void);
bool commanderTest(void);
uint32_t commanderGetInactivityTime(void);
void commanderSetSetpoint(setpoint_t *setpoint, int priority);
int commanderGetActivePriority(void);
void commanderRelaxPriority(void);
void commanderGetSetpoint(setpoint_t *setpoint, const state_t *state);
