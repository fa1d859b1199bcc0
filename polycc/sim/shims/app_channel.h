/* Shim of crazyflie-firmware src/modules/interface/app_channel.h (the app's CRTP channel). */
#pragma once

#include <stdbool.h>
#include <stddef.h>

#define APPCHANNEL_WAIT_FOREVER (-1)
#define APPCHANNEL_MTU (30)

void appchannelSendDataPacketBlock(void *data, size_t length);
int appchannelSendDataPacket(void *data, size_t length);
size_t appchannelReceiveDataPacket(void *buffer, size_t max_length, int timeout_ms);
bool appchannelHasOverflowOccurred(void);
