/* Shim of crazyflie-firmware src/hal/interface/usec_time.h. */
#pragma once

#include <stdint.h>

void usecTimerInit(void);
void usecTimerReset(void);
uint64_t usecTimestamp(void);
