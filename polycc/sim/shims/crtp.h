/* Shim of the part of crazyflie-firmware src/modules/interface/crtp.h apps use. */
#pragma once

#include <stdbool.h>

bool crtpIsConnected(void);
