/* Host P2P radio: the app's broadcasts queue up for Python (shim_p2p_pop), and Python delivers what
 * another drone broadcast through the registered callback (shim_p2p_deliver), as the radio task does. */
#include <string.h>

#include "polycc_shim.h"
#include "radiolink.h"
#include "sim_internal.h"

#define QUEUE 16

static P2PCallback callback;
static P2PPacket txq[QUEUE];
static int txHead, txCount;
static int txLost; /* broadcasts lost to a full queue (the radio's syslink queue would block) */

void shimRadiolinkReset(void)
{
    callback = 0;
    txHead = txCount = txLost = 0;
}

void p2pRegisterCB(P2PCallback cb)
{
    callback = cb;
}

bool radiolinkSendP2PPacketBroadcast(P2PPacket *p2pp)
{
    if (p2pp->size > P2P_MAX_DATA_SIZE) {
        shimAssertFailed(); /* the firmware ASSERTs */
        return false;
    }
    if (txCount == QUEUE) {
        ++txLost;
        return true; /* the firmware returns true whatever the radio does */
    }
    txq[(txHead + txCount) % QUEUE] = *p2pp;
    ++txCount;
    return true;
}

size_t shim_p2p_pop(void *buffer, size_t max_length)
{
    const P2PPacket *p;
    size_t n;
    if (txCount == 0) {
        return 0;
    }
    p = &txq[txHead];
    n = (size_t)p->size + 1u < max_length ? (size_t)p->size + 1u : max_length;
    memcpy(buffer, p->raw, n);
    txHead = (txHead + 1) % QUEUE;
    --txCount;
    return n;
}

int shim_p2p_deliver(const void *raw, size_t length, int rssi)
{
    P2PPacket p;
    if (length < 1u || length > P2P_MAX_DATA_SIZE + 1u) {
        return -1;
    }
    memset(&p, 0, sizeof p);
    memcpy(p.raw, raw, length);
    p.size = (uint8_t)(length - 1u);
    p.rssi = (uint8_t)rssi;
    if (!callback) {
        return -1;
    }
    callback(&p);
    return 0;
}

int shim_p2p_lost(void)
{
    return txLost;
}
