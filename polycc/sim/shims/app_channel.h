/* Shim of crazyflie-firmware src/modules/interface/app_channel.h (the app's CRTP channel). */
#pragma once

#include <stdbool.h>
#include <stddef.h>

#define APPCHANNEL_WAIT_FOREVER (-1)
/* 31 as in the CrazySim SITL fork and the firmware of its time (upstream has 30 since): the larger
 * value, so that an app sizing packets by it is caught (sim_appchannel.c asserts the CRTP limit). */
#define APPCHANNEL_MTU (31)
#define SHIM_CRTP_MAX_DATA_SIZE (30) /* crtp.h CRTP_MAX_DATA_SIZE: crtpSendPacket*() ASSERT(size <= 30) */

void appchannelSendDataPacketBlock(void *data, size_t length);
int appchannelSendDataPacket(void *data, size_t length);
size_t appchannelReceiveDataPacket(void *buffer, size_t max_length, int timeout_ms);
bool appchannelHasOverflowOccurred(void);
