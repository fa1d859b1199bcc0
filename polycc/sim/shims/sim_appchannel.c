/* Host app channel: a queue of packets from the ground (Python pushes) and of the app's replies. */
#include <string.h>

#include "app_channel.h"
#include "polycc_shim.h"
#include "sim_internal.h"

#define QUEUE 16

typedef struct {
    unsigned char data[APPCHANNEL_MTU];
    size_t length;
} packet_t;

static packet_t rxq[QUEUE], txq[QUEUE];
static int rxHead, rxCount, txHead, txCount;
static bool overflow;
static int crtpAsserts; /* sends the firmware would have ASSERTed on (appchannelSendDataPacket) */

void shimAppchannelReset(void)
{
    rxHead = rxCount = txHead = txCount = 0;
    overflow = false;
    crtpAsserts = 0;
}

static int push(packet_t *q, int *head, int *count, const void *data, size_t length)
{
    packet_t *p;
    if (*count == QUEUE) {
        return -1;
    }
    p = &q[(*head + *count) % QUEUE];
    p->length = length > APPCHANNEL_MTU ? APPCHANNEL_MTU : length;
    memcpy(p->data, data, p->length);
    ++*count;
    return 0;
}

static size_t pop(packet_t *q, int *head, int *count, void *buffer, size_t max_length)
{
    packet_t *p;
    size_t n;
    if (*count == 0) {
        return 0;
    }
    p = &q[*head];
    n = p->length < max_length ? p->length : max_length;
    memcpy(buffer, p->data, n);
    *head = (*head + 1) % QUEUE;
    --*count;
    return n;
}

int shim_appchannel_push(const void *data, size_t length)
{
    if (push(rxq, &rxHead, &rxCount, data, length) != 0) {
        overflow = true;
        return -1;
    }
    return 0;
}

size_t shim_appchannel_pop(void *buffer, size_t max_length)
{
    return pop(txq, &txHead, &txCount, buffer, max_length);
}

size_t appchannelReceiveDataPacket(void *buffer, size_t max_length, int timeout_ms)
{
    (void)timeout_ms; /* the host never blocks */
    return pop(rxq, &rxHead, &rxCount, buffer, max_length);
}

/* The firmware's app channel clips to APPCHANNEL_MTU and hands the packet to crtpSendPacket(), which
 * ASSERTs size <= CRTP_MAX_DATA_SIZE; assertFail() stops the motors and resets the Crazyflie. The shim
 * counts such sends (shim_crtp_asserts) and cuts the motors as the firmware would. */
int shim_crtp_asserts(void)
{
    return crtpAsserts;
}

int appchannelSendDataPacket(void *data, size_t length)
{
    size_t sent = length > APPCHANNEL_MTU ? APPCHANNEL_MTU : length;
    if (sent > SHIM_CRTP_MAX_DATA_SIZE) {
        ++crtpAsserts;
        shimAssertFailed();
        return 0;
    }
    return push(txq, &txHead, &txCount, data, length) == 0 ? 1 : 0;
}

void appchannelSendDataPacketBlock(void *data, size_t length)
{
    (void)appchannelSendDataPacket(data, length);
}

bool appchannelHasOverflowOccurred(void)
{
    bool o = overflow;
    overflow = false;
    return o;
}
