/* Shim of crazyflie-firmware src/modules/interface/app.h (declarations only). */
#pragma once

void appInit();
void appMain();
