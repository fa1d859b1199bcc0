/* Shim of the queries of crazyflie-firmware src/modules/interface/supervisor.h. */
#pragma once

#include <stdbool.h>

bool supervisorIsFlying(void);
bool supervisorIsTumbled(void);
bool supervisorIsArmed(void);
bool supervisorIsLocked(void);
bool supervisorIsCrashed(void);
bool supervisorCanFly(void);
