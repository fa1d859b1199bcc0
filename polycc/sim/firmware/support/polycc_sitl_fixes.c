/*
 * polycc_sitl_fixes.c -- build-level work-arounds for bugs of the CrazySim SITL fork
 * (llanesc/crazyflie-firmware sitl-release), compiled into cf2 by polycc/sim/firmware/build.py.
 * No firmware source is copied or edited; build.py only adds this file and, for the
 * affected firmware file, a -D that renames one call.
 *
 * stabilizer-delay-until
 *   src/modules/src/stabilizer.c:278 declares `uint32_t lastWakeTime;` and passes its address
 *   to vTaskDelayUntil(TickType_t *, TickType_t) (stabilizer.c:289).  On the FreeRTOS POSIX
 *   port TickType_t is `unsigned long`, 64 bits (portable/ThirdParty/GCC/Posix/portmacro.h:62),
 *   so vTaskDelayUntil reads and writes 8 bytes: the low half is lastWakeTime, the high half
 *   an uninitialised stack slot.  When that slot is not zero the wake time is >= 2^32, the
 *   "tick count overflowed" branch of vTaskDelayUntil (tasks.c) never delays, and the
 *   priority-5 stabilizer task spins in its "Wait for sensor calibration" loop forever,
 *   starving every lower-priority task (CRTP RX, sensors, param, log, app): cf2 boots, prints
 *   "Wait for sensor calibration...", and never answers.  On the real Crazyflie TickType_t is
 *   uint32_t (portable/GCC/ARM_CM4F/portmacro.h:63) and the code is correct.
 *
 *   build.py compiles stabilizer.c with -DvTaskDelayUntil=polycc_sitl_vTaskDelayUntil_u32;
 *   this function takes the 32-bit variable the caller really passes.
 */
#include <stdint.h>

#include "FreeRTOS.h"
#include "task.h"

void polycc_sitl_vTaskDelayUntil_u32(uint32_t *pxPreviousWakeTime, TickType_t xTimeIncrement);

void polycc_sitl_vTaskDelayUntil_u32(uint32_t *pxPreviousWakeTime, TickType_t xTimeIncrement)
{
    TickType_t t = (TickType_t)*pxPreviousWakeTime;
    vTaskDelayUntil(&t, xTimeIncrement);
    *pxPreviousWakeTime = (uint32_t)t;
}

/*
 * debug-rx-drops (diagnostic, off by default)
 *   build.py compiles src/hal/src/socketlink.c with
 *   -DxQueueGenericSend=polycc_sitl_dbg_xQueueGenericSend, so the reader task's
 *   xQueueSend(crtpPacketDelivery, &p, 0) (socketlink.c:95) comes here: every packet the
 *   firmware drops because its 5-deep RX queue is full is printed with the CLOCK_MONOTONIC
 *   time (comparable with Python's time.monotonic()), the tick count and the CRTP header.
 */
#include <stdio.h>
#include <time.h>

#include "queue.h"

BaseType_t polycc_sitl_dbg_xQueueGenericSend(QueueHandle_t xQueue, const void * const pvItemToQueue,
                                             TickType_t xTicksToWait, const BaseType_t xCopyPosition);

BaseType_t polycc_sitl_dbg_xQueueGenericSend(QueueHandle_t xQueue, const void * const pvItemToQueue,
                                             TickType_t xTicksToWait, const BaseType_t xCopyPosition)
{
    static unsigned long drops, sent;
    BaseType_t r = xQueueGenericSend(xQueue, pvItemToQueue, xTicksToWait, xCopyPosition);
    if (r != pdTRUE) {
        struct timespec ts;
        const uint8_t *pk = (const uint8_t *)pvItemToQueue; /* CRTPPacket: size, then header */
        clock_gettime(CLOCK_MONOTONIC, &ts);
        ++drops;
        printf("RXDROP t=%ld.%06ld tick=%lu hdr=0x%02x b1=0x%02x size=%u drops=%lu of %lu\n",
               (long)ts.tv_sec, ts.tv_nsec / 1000L, (unsigned long)xTaskGetTickCount(), pk[1], pk[2],
               (unsigned)pk[0], drops, drops + sent);
    } else {
        ++sent;
    }
    return r;
}

/*
 * deck-params
 *   The fork's sitl_make/CMakeLists.txt leaves the deck subsystem out (deck/core and every driver
 *   are commented out), so its param TOC has no `deck` group at all.  On a real Crazyflie each deck
 *   driver registers its presence flag (e.g. src/deck/drivers/src/zranger.c: PARAM_ADD_CORE(
 *   PARAM_UINT8 | PARAM_RONLY, bcZRanger, &isInit)), 0 when that deck is not attached; cfclient's
 *   flight, lighthouse and LED-ring tabs read them on connect and raise KeyError without the group.
 *   build.py compiles this file with -DPOLYCC_SITL_DECK_PARAMS: the same read-only flags, all 0,
 *   as on a Crazyflie with no deck (the SITL has no deck bus).
 */
#ifdef POLYCC_SITL_DECK_PARAMS
#include "param.h"

static uint8_t polycc_sitl_no_deck;

PARAM_GROUP_START(deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcFlow, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcFlow2, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcZRanger, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcZRanger2, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcMultiranger, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcLighthouse4, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcLoco, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcDWM1000, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcAI, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcLedRing, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcUSD, &polycc_sitl_no_deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcBuzzer, &polycc_sitl_no_deck)
PARAM_GROUP_STOP(deck)
#endif

/*
 * p2p
 *   The fork's sitl_make/CMakeLists.txt leaves src/hal/src/radiolink.c out (the SITL has no nRF: its
 *   only link is socketlink.c's UDP socket), so an app calling the radio's peer-to-peer broadcast
 *   (radiolink.h: p2pRegisterCB, radiolinkSendP2PPacketBroadcast) does not link.  On a real Crazyflie
 *   the nRF51 broadcasts a P2P packet (port, then up to P2P_MAX_DATA_SIZE bytes) to every drone on the
 *   same radio channel and hands each one it hears to the registered callback, from the syslink task
 *   (radiolink.c: radiolinkSyslinkDispatch, SYSLINK_RADIO_P2P_BROADCAST).
 *   build.py compiles this file with -DPOLYCC_SITL_P2P: a broadcast leaves as one CRTP packet on port
 *   POLYCC_SITL_P2P_CRTP_PORT (unused by the firmware; data = the P2P packet's raw bytes: port, data)
 *   through the socket link, where polycc's bridge (polycc/sim/firmware/bridge.py --air) hands it to
 *   every other instance; such a packet coming in reaches the callback from the CRTP RX task.  The
 *   CRTP payload is 30 bytes, so a P2P packet with more than 29 data bytes is refused (false).
 */
#ifdef POLYCC_SITL_P2P
#include <stdbool.h>
#include <string.h>

#include "crtp.h"
#include "radiolink.h"

#define POLYCC_SITL_P2P_CRTP_PORT 0x0B

static volatile P2PCallback polycc_sitl_p2p_cb;

static void polycc_sitl_p2p_rx(CRTPPacket *pk)
{
    P2PPacket p;
    P2PCallback cb = polycc_sitl_p2p_cb;
    if (pk->size < 1u || cb == 0) {
        return;
    }
    memset(&p, 0, sizeof p);
    memcpy(p.raw, pk->data, pk->size);
    p.size = (uint8_t)(pk->size - 1u);
    p.rssi = 40u; /* a strong signal (-40 dBm): the SITL air loses nothing */
    cb(&p);
}

void p2pRegisterCB(P2PCallback cb)
{
    polycc_sitl_p2p_cb = cb;
    crtpRegisterPortCB(POLYCC_SITL_P2P_CRTP_PORT, polycc_sitl_p2p_rx);
}

bool radiolinkSendP2PPacketBroadcast(P2PPacket *p)
{
    CRTPPacket pk;
    if (p->size + 1u > CRTP_MAX_DATA_SIZE) {
        return false;
    }
    memset(&pk, 0, sizeof pk);
    pk.header = CRTP_HEADER(POLYCC_SITL_P2P_CRTP_PORT, 0);
    pk.size = (uint8_t)(p->size + 1u);
    memcpy(pk.data, p->raw, pk.size);
    return crtpSendPacket(&pk) == pdTRUE;
}
#endif
