/* Shim of the public (app) API of crazyflie-firmware src/modules/interface/crtp_commander_high_level.h. */
#pragma once

#include <stdbool.h>
#include <stdint.h>

#include "stabilizer_types.h"

bool crtpCommanderHighLevelIsStopped(void);
bool crtpCommanderHighLevelIsTrajectoryFinished(void);
int crtpCommanderHighLevelTakeoff(const float absoluteHeight_m, const float duration_s);
int crtpCommanderHighLevelTakeoffYaw(const float absoluteHeight_m, const float duration_s, const float yaw);
int crtpCommanderHighLevelLand(const float absoluteHeight_m, const float duration_s);
int crtpCommanderHighLevelLandYaw(const float absoluteHeight_m, const float duration_s, const float yaw);
int crtpCommanderHighLevelStop(void);
int crtpCommanderHighLevelGoTo(const float x, const float y, const float z, const float yaw, const float duration_s,
                               const bool relative);
void crtpCommanderHighLevelTellState(const state_t *state);
