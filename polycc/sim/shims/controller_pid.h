/* Shim of crazyflie-firmware src/modules/interface/controller/controller_pid.h.  The host version
 * records the setpoint it gets (the stabilizer step reports it; polycc/sim/dynamics.py models the PID). */
#pragma once

#include <stdbool.h>

#include "stabilizer_types.h"

void controllerPidInit(void);
bool controllerPidTest(void);
void controllerPid(control_t *control, const setpoint_t *setpoint, const sensorData_t *sensors, const state_t *state,
                   const stabilizerStep_t stabilizerStep);
