/*
 * polycc_app.c -- Crazyflie app layer: certified polytope CBF safety filter around a CLF
 * go-to-goal controller, flying world-frame velocity setpoints (states: polycc_app.h).
 *
 * The only polycc C file that includes firmware headers.  The host SITL compiles this very
 * file against declaration shims (polycc/sim/shims/) with the same flags, and the real-firmware
 * SITL (polycc/sim/firmware/) compiles it into the CrazySim firmware.
 *
 * Each tick (polycc_app_tick, at param polycc.rateHz, default 500 Hz, lowered when the scene's
 * certified worst case needs it):
 *   1. answers app-channel packets (heartbeats) with the app's status;
 *   2. decides whether it may have control: enabled, flying (supervisor), the high-level
 *      commander idle or done, PID controller, link up;
 *   3. reads stateEstimate.x/y/z through the log API (and kalman.varX/Y/Z when present);
 *   4. runs polycc_step() of the kernel on the generated scene (polytopes.h), with the speed
 *      limit lowered near obstacles by the braking term (polycc_app.h, POLYCC_APP_BRAKE_*);
 *   5. sends a world-frame velocity setpoint with commanderSetSetpoint at priority EXTRX, every
 *      tick while engaged (so the commander's 500 ms / 2 s watchdog never fires);
 *   a bad or stale estimate, psi < 0 or a kernel refusal holds the position where it began.
 *   Leaving control goes through the high-level commander (hold, or land on link loss), never
 *   through a stop setpoint.
 *
 * Build: -ffp-contract=off (bit-exact kernel) and -fno-math-errno; see src/Kbuild.
 */
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

/* The firmware's Kconfig symbols (CONFIG_CONTROLLER_OOT) before controller.h reads them: the
 * firmware force-includes nothing for an out-of-tree app, and debug.h pulls autoconf.h in too late. */
#if defined(__has_include)
#if __has_include("autoconf.h")
#include "autoconf.h"
#endif
#endif
#include "app.h"
#include "app_channel.h"
#include "commander.h"
#include "config.h" /* CMD_HIGH_LEVEL_TASK_PRI */
#include "controller.h"
#include "crtp.h"
#include "crtp_commander_high_level.h"
#include "FreeRTOS.h"
#include "log.h"
#include "param.h"
#include "supervisor.h"
#include "task.h"
#include "usec_time.h"

#define DEBUG_MODULE "POLYCC"
#include "debug.h"

#include "polycc_app.h"
#include "polycc_controller.h"
#include "polycc_kernel.h"
#include "polycc_swarm.h" /* swarm: neighbour terms (docs/swarm.md) */
#include "radiolink.h"    /* swarm: P2P broadcast (p2pRegisterCB, radiolinkSendP2PPacketBroadcast) */

/* The generated scene: -DPOLYCC_SCENE_HEADER='"/abs/path/polytopes.h"' or polytopes.h on the include path. */
#ifdef POLYCC_SCENE_HEADER
#include POLYCC_SCENE_HEADER
#else
#include "polytopes.h"
#endif

#ifndef POLYCC_HEADER_FORMAT
#error "polytopes.h does not define POLYCC_HEADER_FORMAT: it is not a polycc scene header; regenerate it with `polycc build`"
#elif POLYCC_HEADER_FORMAT != POLYCC_SCENE_FORMAT
#error "polytopes.h was generated for another scene layout format than this app (POLYCC_SCENE_FORMAT); regenerate it with the polycc that ships this app"
#endif
#ifndef POLYCC_SCENE_KAPPA
#error "polytopes.h does not define POLYCC_SCENE_KAPPA; regenerate it with `polycc build`"
#endif
#ifndef POLYCC_SCENE_WORST_CYCLES
#error "polytopes.h does not define POLYCC_SCENE_WORST_CYCLES; regenerate it with `polycc build`"
#endif

/* Commander priority of the app's setpoints: above the high-level commander and above CRTP
 * setpoints from a ground station, which are ignored while the app is engaged. */
#ifndef POLYCC_APP_PRIORITY
#define POLYCC_APP_PRIORITY COMMANDER_PRIORITY_EXTRX
#endif

/* ---- parameter group polycc (written by the param task; snapshotted once per tick) ---- */
static uint8_t pEnable;
static float pGoalX, pGoalY, pGoalZ;
static float pVmax, pBeta, pClfGain, pRadius;
static uint16_t pRateHz;

/* ---- log group polycc ---- */
static float lPsi, lUx, lUy, lUz;
static float lRadius; /* the radius the filter flies with, m (flightRadius) */
static uint8_t lActive, lStatus;
static uint32_t lEvalUs;
static uint32_t lLate; /* app ticks that started more than one RTOS tick after their scheduled wake */
static uint16_t lRate;

/* ---- state ---- */
static logVarId_t idX, idY, idZ, idVx, idVy, idVz, idYaw, idVarX, idVarY, idVarZ;
static bool haveEstimate, haveVelocity, haveYaw, haveVariance;
static bool engaged;     /* the app streams setpoints and owns the vehicle */
static bool holding;     /* a fallback holds holdPos */
static float holdPos[3]; /* where the fallback began */
static float lastGood[3];
static bool haveLastGood;
static bool psiFresh; /* the previous app tick evaluated the kernel (trace.out.psi is one period old) */
static bool heartbeatSeen;
static uint32_t lastHeartbeat; /* tick */
static bool linkLostLatched; /* the last engagement ended in a link-loss landing (cleared by enable) */
static logVarId_t idThrust;
static bool haveThrust;
static polycc_app_trace_t trace;
static logVarId_t idZi;       /* posCtl.Zi: the PID position controller's z integral output, m/s */
static paramVarId_t idZKp;    /* posCtlPid.zKp, 1/s */
static bool haveZi, haveZKp;
static bool settling;         /* disabled in the air: holding until Zi has decayed (status 13) */
static uint32_t settleStart;  /* tick */
static uint32_t lastBits[3];
static uint32_t sameTicks; /* ms for which the estimate bits did not change */
static setpoint_t setpoint;

/* ---- swarm: neighbours fed over the app channel (docs/swarm.md) ---- */
static polycc_swarm_t swarm;
static float pSwarmV;       /* param polycc.swarmV: the neighbours' speed bound, m/s */
static uint8_t lNbr;        /* log polycc.nNbr */
static uint32_t swarmTick;  /* tick of the last ageing */
static uint32_t swarmPeriodMs = 1u; /* the last period: a queued report waited at most this long */
static uint8_t pSwarmN;     /* param polycc.swarmN: hold while fewer neighbours are known */
static uint8_t pSwarmId;    /* param polycc.swarmId: own P2P id, 0 = no broadcast */
static uint16_t pP2pMs;     /* param polycc.p2pMs: own broadcast period, ms (0 = none) */
static uint16_t pP2pAgeMs;  /* param polycc.p2pAgeMs: stated age of own broadcasts, ms */
static uint32_t lastP2pTx;  /* tick of the last own broadcast */
static uint16_t lP2pRx, lP2pTx, lP2pDrop; /* log polycc.p2pRx/p2pTx/p2pDrop */

/* P2P records heard by the radio task, read by the app task: single producer, single consumer ring.
 * The producer writes a slot, then publishes it by advancing p2pHead; the consumer reads slots up to
 * p2pHead, then frees them by advancing p2pTail. Full: the record is dropped and counted. */
typedef struct {
    uint8_t rec[POLYCC_APP_NBR_BYTES];
    uint32_t tick; /* arrival */
} p2pRecord_t;
static p2pRecord_t p2pRing[POLYCC_APP_P2P_RING];
static volatile uint32_t p2pHead, p2pTail;
static volatile uint32_t p2pRejected; /* written by the producer only */

static uint32_t floatBits(float f)
{
    uint32_t b;
    memcpy(&b, &f, sizeof b);
    return b;
}

static bool coordOk(float v)
{
    return v >= -POLYCC_APP_POS_LIMIT && v <= POLYCC_APP_POS_LIMIT; /* false for NaN */
}

/* Shortest period (ticks) at which the scene's certified worst case fits the CPU share. */
static uint32_t minPeriodTicks(void)
{
    const uint64_t perTick = (uint64_t)POLYCC_APP_CPU_HZ / (uint64_t)configTICK_RATE_HZ;
    const uint64_t need = ((uint64_t)POLYCC_SCENE_WORST_CYCLES + POLYCC_APP_SWARM_WORST_CYCLES) * 100u;
    const uint64_t avail = perTick * POLYCC_APP_CPU_SHARE_PERCENT;
    uint64_t t = (need + avail - 1u) / avail;
    return t < 1u ? 1u : (uint32_t)t;
}

/* rateHz clamped to [POLYCC_APP_MIN_RATE_HZ, tick rate], rounded to whole ticks, and lowered
 * until the worst case fits; lRate logs the rate it gives. */
static uint32_t periodTicks(uint16_t rateHz)
{
    uint32_t r = rateHz < POLYCC_APP_MIN_RATE_HZ ? POLYCC_APP_MIN_RATE_HZ : rateHz;
    uint32_t t = (configTICK_RATE_HZ + r / 2u) / r;
    uint32_t tmin = minPeriodTicks();
    if (t < 1u) {
        t = 1u;
    }
    if (t < tmin) {
        t = tmin;
    }
    lRate = (uint16_t)(configTICK_RATE_HZ / t);
    return t;
}

static bool tooSlow(void)
{
    return minPeriodTicks() > configTICK_RATE_HZ / POLYCC_APP_MIN_RATE_HZ;
}

static void send(void)
{
    commanderSetSetpoint(&setpoint, POLYCC_APP_PRIORITY);
    engaged = true;
}

static void sendVelocity(float vx, float vy, float vz)
{
    memset(&setpoint, 0, sizeof setpoint);
    setpoint.mode.x = modeVelocity;
    setpoint.mode.y = modeVelocity;
    setpoint.mode.z = modeVelocity;
    setpoint.mode.yaw = modeVelocity; /* hold heading: yaw rate 0 */
    setpoint.velocity.x = vx;
    setpoint.velocity.y = vy;
    setpoint.velocity.z = vz;
    setpoint.attitudeRate.yaw = 0.0f;
    setpoint.velocity_body = false; /* world frame */
    send();
    lUx = vx;
    lUy = vy;
    lUz = vz;
    holding = false;
}

/* The PID cascade flies the setpoints: the stock PID controller, or the shield's out-of-tree controller,
 * which runs the same PID after the shield (polycc_controller.c). */
static bool runsPid(void)
{
#ifdef CONFIG_CONTROLLER_OOT
    if (controllerGetType() == ControllerTypeOot) {
        return true;
    }
#endif
    return controllerGetType() == ControllerTypePID;
}

/* posCtl.Zi, the PID position controller's z integral output, m/s (0 without it). */
static float zIntegral(void)
{
    float zi = haveZi ? logGetFloat(idZi) : 0.0f;
    return zi == zi ? zi : 0.0f;
}

float polycc_app_pid_zi(void)
{
    return runsPid() ? zIntegral() : 0.0f;
}

/* Metres to subtract from a position hold's z so that the PID position controller's stale z integral
 * (posCtl.Zi) is cancelled: its velocity command is then zKp (z_hold - z), a pure proportional hold
 * (polycc_app.h).  0 without the PID cascade or the log variable. */
static float ziOffset(void)
{
    float zi, kp, off;
    if (!haveZi || !runsPid()) {
        return 0.0f;
    }
    zi = zIntegral();
    kp = haveZKp ? paramGetFloat(idZKp) : POLYCC_APP_POS_Z_KP;
    if (!(kp > 0.1f)) {
        return 0.0f;
    }
    off = zi / kp;
    if (off > POLYCC_APP_ZI_OFFSET_MAX) {
        off = POLYCC_APP_ZI_OFFSET_MAX;
    }
    if (off < -POLYCC_APP_ZI_OFFSET_MAX) {
        off = -POLYCC_APP_ZI_OFFSET_MAX;
    }
    return off;
}

float polycc_app_pid_zi_offset(void)
{
    return ziOffset();
}

/* Position hold at the point where the fallback began (x: the estimate now, if valid). */
static void holdPosition(const float *x)
{
    if (!holding) {
        const float *p = x != 0 ? x : (haveLastGood ? lastGood : 0);
        if (p == 0) {
            /* no estimate was ever valid: nothing to hold, and nothing was sent before either */
            return;
        }
        memcpy(holdPos, p, sizeof holdPos);
        holding = true;
    }
    memset(&setpoint, 0, sizeof setpoint);
    setpoint.mode.x = modeAbs;
    setpoint.mode.y = modeAbs;
    setpoint.mode.z = modeAbs;
    setpoint.mode.yaw = modeVelocity;
    setpoint.position.x = holdPos[0];
    setpoint.position.y = holdPos[1];
    setpoint.position.z = holdPos[2] - ziOffset();
    setpoint.attitudeRate.yaw = 0.0f;
    send();
    lUx = 0.0f;
    lUy = 0.0f;
    lUz = 0.0f;
}

static void readVector(logVarId_t a, logVarId_t b, logVarId_t c, bool have, float out[3])
{
    out[0] = have ? logGetFloat(a) : 0.0f;
    out[1] = have ? logGetFloat(b) : 0.0f;
    out[2] = have ? logGetFloat(c) : 0.0f;
}

/* The hold of a settling hand-over: the high-level go_to to holdPos, then the priority relaxed. */
static void finishHandOver(void)
{
    float yaw = haveYaw ? logGetFloat(idYaw) * (3.14159265358979f / 180.0f) : 0.0f;
    settling = false;
    if (crtpCommanderHighLevelGoTo(holdPos[0], holdPos[1], holdPos[2], yaw, POLYCC_APP_HANDOVER_MIN_S, false) != 0) {
        holdPosition(0);
        return;
    }
    trace.handovers += 1u;
    commanderRelaxPriority();
    engaged = false;
    holding = false;
}

/* The high-level commander carries out a command from the ground (takeoff, go_to, land, ...) in its own task,
 * CMD_HIGH_LEVEL_TASK_PRI (config.h), which preempts the app's.  A command carried out between the hand-over's
 * check of the planner (crtpCommanderHighLevelIsStopped) and what the hand-over then sends would be lost: a hold
 * setpoint above HIGHLEVEL stops the planner (commanderSetSetpoint), a go_to replaces the plan.  A user's land
 * sent while the app settled was lost that way, and the vehicle hovered on (docs/barrier.md, "a land lost to
 * the hand-over").  So the hand-over runs above that task: a command that arrives meanwhile is carried out right
 * after it, and the next app tick sees the planner running and lets go.  The raised section blocks on nothing
 * the high-level task can hold (that task cannot be preempted by the app), and lasts one go_to plan at most. */
#define POLYCC_APP_HANDOVER_TASK_PRI (CMD_HIGH_LEVEL_TASK_PRI + 1)

static void handOverStep(void);

/* One hand-over step (handOverStep) above the high-level commander's task. */
static void handOverHold(void)
{
    UBaseType_t prio = uxTaskPriorityGet(NULL);
    if (prio < POLYCC_APP_HANDOVER_TASK_PRI) {
        vTaskPrioritySet(NULL, POLYCC_APP_HANDOVER_TASK_PRI);
    }
    handOverStep();
    if (prio < POLYCC_APP_HANDOVER_TASK_PRI) {
        vTaskPrioritySet(NULL, prio); /* a command that came meanwhile is carried out here */
    }
}

/* Give the vehicle to the high-level commander, holding position: go_to the stopping point of
 * a POLYCC_APP_HANDOVER_ACC deceleration (no further than half the last clearance), then relax
 * the priority.  If the high-level commander refuses, the app keeps holding the position itself.
 * If the planner is already running (each app setpoint stops it, so the ground sent a takeoff,
 * go_to or land since the last one, e.g. a land right after enable = 0), its plan is kept: the
 * app only relaxes the priority.
 * With the PID controller and a wound-up z integral, the app first holds the stopping point itself
 * (settling, status 13) until the integral has decayed, a high-level command arrives or
 * POLYCC_APP_SETTLE_MAX_MS passed (polycc_app.h).
 * Runs above the high-level commander's task (handOverHold): while the app holds, a land from the ground is
 * either seen by the check below or carried out after this step's setpoint. */
static void handOverStep(void)
{
    float x[3], v[3], yaw = 0.0f, s, d, T;
    int i;
    if (!crtpCommanderHighLevelIsStopped()) {
        /* a high-level command from the ground started a trajectory since the last tick: it takes over */
        trace.handovers += 1u;
        settling = false;
        commanderRelaxPriority();
        engaged = false;
        holding = false;
        return;
    }
    if (settling) {
        if (runsPid() && fabsf(zIntegral()) > POLYCC_APP_SETTLE_ZI &&
            xTaskGetTickCount() - settleStart < M2T(POLYCC_APP_SETTLE_MAX_MS)) {
            holdPosition(0);
            return;
        }
        finishHandOver();
        return;
    }
    readVector(idX, idY, idZ, haveEstimate, x);
    readVector(idVx, idVy, idVz, haveVelocity, v);
    if (!haveEstimate || !coordOk(x[0]) || !coordOk(x[1]) || !coordOk(x[2])) {
        if (!haveLastGood) {
            commanderRelaxPriority();
            engaged = false;
            return;
        }
        memcpy(x, lastGood, sizeof x);
        v[0] = v[1] = v[2] = 0.0f;
    }
    if (haveYaw) {
        yaw = logGetFloat(idYaw) * (3.14159265358979f / 180.0f);
    }
    s = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    d = s * s / (2.0f * POLYCC_APP_HANDOVER_ACC);
    if (trace.calls > 0u && d > 0.5f * trace.out.psi) {
        d = trace.out.psi > 0.0f ? 0.5f * trace.out.psi : 0.0f;
    }
    T = s > 0.0f ? 2.0f * d / s : 0.0f;
    if (!(T >= POLYCC_APP_HANDOVER_MIN_S)) {
        T = POLYCC_APP_HANDOVER_MIN_S;
    }
    for (i = 0; i < 3; ++i) {
        trace.handover[i] = s > 0.0f ? x[i] + v[i] * (d / s) : x[i];
    }
    trace.handover[3] = T;
    if (haveZi && runsPid() && fabsf(zIntegral()) > POLYCC_APP_SETTLE_ZI) {
        memcpy(holdPos, trace.handover, sizeof holdPos);
        holding = true;
        settling = true;
        settleStart = xTaskGetTickCount();
        holdPosition(0);
        return;
    }
    if (crtpCommanderHighLevelGoTo(trace.handover[0], trace.handover[1], trace.handover[2], yaw, T, false) != 0) {
        holdPosition(haveEstimate ? x : 0);
        return;
    }
    trace.handovers += 1u;
    commanderRelaxPriority();
    engaged = false;
    holding = false;
}

/* Link lost: a high-level landing from here, then the priority relaxed; enable is cleared so a
 * reconnecting ground does not take over mid-landing. */
static void handOverLand(void)
{
    float x[3], T;
    readVector(idX, idY, idZ, haveEstimate, x);
    T = coordOk(x[2]) && x[2] > 0.0f ? x[2] / POLYCC_APP_LAND_SPEED : POLYCC_APP_LAND_MIN_S;
    if (!(T >= POLYCC_APP_LAND_MIN_S)) {
        T = POLYCC_APP_LAND_MIN_S;
    }
    settling = false;
    if (crtpCommanderHighLevelLand(0.0f, T) != 0) {
        holdPosition(haveEstimate && coordOk(x[0]) ? x : 0);
        return;
    }
    trace.landings += 1u;
    commanderRelaxPriority();
    engaged = false;
    holding = false;
    pEnable = 0u;
}

/* Swarm: the fields of an 18-byte neighbour record (polycc_app.h: 'N', id, x, y, z, age ms, radius mm). */
static void decodeNbr(const uint8_t *rec, float pj[3], uint16_t *age, float *radius)
{
    uint16_t rmm;
    memcpy(pj, rec + 2, 12);
    memcpy(age, rec + 14, 2);
    memcpy(&rmm, rec + 16, 2);
    *radius = (float)rmm * 0.001f;
}

/* Radio task (P2PCallback): one P2P packet heard; a neighbour record on POLYCC_APP_P2P_PORT goes into
 * the ring with its arrival tick, anything else on that port is counted and dropped. */
static void onP2p(P2PPacket *p)
{
    uint32_t head = p2pHead;
    if (p->port != POLYCC_APP_P2P_PORT) {
        return; /* another app's port */
    }
    if (p->size != POLYCC_APP_NBR_BYTES || p->data[0] != POLYCC_APP_NBR_MAGIC ||
        head - p2pTail >= POLYCC_APP_P2P_RING) {
        p2pRejected = p2pRejected + 1u;
        return;
    }
    memcpy(p2pRing[head % POLYCC_APP_P2P_RING].rec, p->data, POLYCC_APP_NBR_BYTES);
    p2pRing[head % POLYCC_APP_P2P_RING].tick = (uint32_t)xTaskGetTickCount();
    __sync_synchronize(); /* the slot is written before it is published */
    p2pHead = head + 1u;
}

/* App task: every P2P record heard since the last tick into the neighbour table, aged by its stated age
 * plus the time since it arrived; a record stating "forget" or with the own id is refused. */
static void drainP2p(const float x[3])
{
    uint32_t tail = p2pTail, head = p2pHead, now = (uint32_t)xTaskGetTickCount();
    __sync_synchronize(); /* the slots up to head are read after head */
    for (; tail != head; ++tail) {
        const p2pRecord_t *r = &p2pRing[tail % POLYCC_APP_P2P_RING];
        float pj[3], rj;
        uint16_t age;
        decodeNbr(r->rec, pj, &age, &rj);
        if (age == POLYCC_APP_NBR_FORGET || (pSwarmId != 0u && r->rec[1] == pSwarmId) ||
            polycc_swarm_report(&swarm, r->rec[1], pj, (uint32_t)age + (now - r->tick) * (1000u / configTICK_RATE_HZ),
                                rj, x) < 0) {
            lP2pDrop = (uint16_t)(lP2pDrop + 1u);
        } else {
            lP2pRx = (uint16_t)(lP2pRx + 1u);
        }
    }
    __sync_synchronize(); /* the slots are read before they are freed */
    p2pTail = tail;
    lP2pDrop = (uint16_t)(lP2pDrop + p2pRejected);
    p2pRejected = 0u; /* a rejection between the read and this write is lost from the count, not the table */
    lNbr = (uint8_t)swarm.count;
}

/* Every polycc.p2pMs: the own estimate as a P2P neighbour record (swarmId != 0). */
static void broadcastP2p(const float x[3])
{
    P2PPacket pk;
    uint32_t now = (uint32_t)xTaskGetTickCount();
    uint16_t rmm;
    if (pSwarmId == 0u || pP2pMs == 0u || (now - lastP2pTx) * (1000u / configTICK_RATE_HZ) < pP2pMs || !coordOk(x[0]) ||
        !coordOk(x[1]) || !coordOk(x[2])) {
        return;
    }
    lastP2pTx = now;
    rmm = 0xffffu; /* radius in mm, rounded up: the others' buffer is never smaller than the own radius */
    if (pRadius >= 0.0f && pRadius < 65.0f) {
        float mm = pRadius * 1000.0f;
        rmm = (uint16_t)mm;
        if ((float)rmm < mm) {
            rmm = (uint16_t)(rmm + 1u);
        }
    }
    memset(&pk, 0, sizeof pk);
    pk.port = POLYCC_APP_P2P_PORT;
    pk.size = (uint8_t)POLYCC_APP_NBR_BYTES;
    pk.data[0] = POLYCC_APP_NBR_MAGIC;
    pk.data[1] = pSwarmId;
    memcpy(pk.data + 2, x, 12);
    memcpy(pk.data + 14, &pP2pAgeMs, 2);
    memcpy(pk.data + 16, &rmm, 2);
    if (radiolinkSendP2PPacketBroadcast(&pk)) {
        lP2pTx = (uint16_t)(lP2pTx + 1u);
    }
}

/* Answers every app-channel packet with the status (polycc_app.h: POLYCC_APP_REPLY_BYTES). */
static void serviceAppChannel(void)
{
    uint8_t rx[APPCHANNEL_MTU], tx[APPCHANNEL_MTU];
    size_t n;
    while ((n = appchannelReceiveDataPacket(rx, sizeof rx, 0)) > 0u) {
        float x[3];
        size_t echo = n > POLYCC_APP_TX_MAX - POLYCC_APP_REPLY_BYTES ? POLYCC_APP_TX_MAX - POLYCC_APP_REPLY_BYTES : n;
        heartbeatSeen = true;
        lastHeartbeat = xTaskGetTickCount();
        readVector(idX, idY, idZ, haveEstimate, x);
        if (n == POLYCC_APP_NBR_BYTES && rx[0] == POLYCC_APP_NBR_MAGIC && haveEstimate) { /* swarm: a neighbour */
            float pj[3], rj;
            uint16_t age;
            decodeNbr(rx, pj, &age, &rj);
            if (age == POLYCC_APP_NBR_FORGET) { /* the ground says it landed or left */
                (void)polycc_swarm_forget(&swarm, rx[1]);
            } else {
                (void)polycc_swarm_report(&swarm, rx[1], pj, (uint32_t)age + swarmPeriodMs, rj, x);
            }
            lNbr = (uint8_t)swarm.count;
        }
        tx[0] = lStatus;
        tx[1] = pEnable;
        memcpy(tx + 2, &lPsi, 4);
        memcpy(tx + 6, x, 12);
        memcpy(tx + POLYCC_APP_REPLY_BYTES, rx, echo);
        (void)appchannelSendDataPacket(tx, POLYCC_APP_REPLY_BYTES + echo);
    }
}

static bool linkLost(void)
{
    if (!crtpIsConnected()) {
        return true;
    }
    return heartbeatSeen && (xTaskGetTickCount() - lastHeartbeat) > M2T(POLYCC_APP_LINK_TIMEOUT_MS);
}

/* Estimate check; returns POLYCC_STATUS_OK or the reason to hold. */
static uint8_t readEstimate(float x[3], uint32_t period)
{
    int i;
    bool same = true;
    if (!haveEstimate) {
        return POLYCC_STATUS_NO_ESTIMATE;
    }
    x[0] = logGetFloat(idX);
    x[1] = logGetFloat(idY);
    x[2] = logGetFloat(idZ);
    for (i = 0; i < 3; ++i) {
        uint32_t b = floatBits(x[i]);
        same = same && b == lastBits[i];
        lastBits[i] = b;
    }
    sameTicks = same ? sameTicks + period : 0u;
    if (!coordOk(x[0]) || !coordOk(x[1]) || !coordOk(x[2])) {
        return POLYCC_STATUS_BAD_ESTIMATE;
    }
    if (haveVariance) {
        float vx = logGetFloat(idVarX), vy = logGetFloat(idVarY), vz = logGetFloat(idVarZ);
        /* written so that NaN fails */
        if (!(vx <= POLYCC_APP_POS_VAR_MAX && vy <= POLYCC_APP_POS_VAR_MAX && vz <= POLYCC_APP_POS_VAR_MAX)) {
            return POLYCC_STATUS_BAD_ESTIMATE;
        }
    }
    if (sameTicks >= M2T(POLYCC_APP_STALE_MS)) {
        return POLYCC_STATUS_STALE_ESTIMATE;
    }
    return POLYCC_STATUS_OK;
}

void polycc_app_init(void)
{
    pEnable = 0u;
    pGoalX = 0.0f;
    pGoalY = 0.0f;
    pGoalZ = POLYCC_APP_DEFAULT_GOAL_Z;
    pVmax = POLYCC_APP_DEFAULT_VMAX;
    pBeta = POLYCC_APP_DEFAULT_BETA;
    pClfGain = POLYCC_APP_DEFAULT_CLF_GAIN;
    pRadius = POLYCC_APP_DEFAULT_RADIUS;
    pRateHz = POLYCC_APP_DEFAULT_RATE_HZ;
    lPsi = 0.0f;
    lRadius = POLYCC_APP_DEFAULT_RADIUS;
    lUx = 0.0f;
    lUy = 0.0f;
    lUz = 0.0f;
    lActive = 0u;
    lStatus = POLYCC_STATUS_DISABLED;
    lEvalUs = 0u;
    engaged = false;
    holding = false;
    haveLastGood = false;
    heartbeatSeen = false;
    lastHeartbeat = 0u;
    linkLostLatched = false;
    sameTicks = 0u;
    lastBits[0] = 0xffffffffu; /* a NaN pattern the estimate never starts with */
    lastBits[1] = 0xffffffffu;
    lastBits[2] = 0xffffffffu;
    idX = logGetVarId("stateEstimate", "x");
    idY = logGetVarId("stateEstimate", "y");
    idZ = logGetVarId("stateEstimate", "z");
    idVx = logGetVarId("stateEstimate", "vx");
    idVy = logGetVarId("stateEstimate", "vy");
    idVz = logGetVarId("stateEstimate", "vz");
    idYaw = logGetVarId("stateEstimate", "yaw");
    idThrust = logGetVarId("stabilizer", "thrust");
    idVarX = logGetVarId("kalman", "varX");
    idVarY = logGetVarId("kalman", "varY");
    idVarZ = logGetVarId("kalman", "varZ");
    haveEstimate = logVarIdIsValid(idX) && logVarIdIsValid(idY) && logVarIdIsValid(idZ);
    haveVelocity = logVarIdIsValid(idVx) && logVarIdIsValid(idVy) && logVarIdIsValid(idVz);
    haveYaw = logVarIdIsValid(idYaw);
    haveThrust = logVarIdIsValid(idThrust);
    haveVariance = logVarIdIsValid(idVarX) && logVarIdIsValid(idVarY) && logVarIdIsValid(idVarZ);
    idZi = logGetVarId("posCtl", "Zi");
    haveZi = logVarIdIsValid(idZi);
    idZKp = paramGetVarId("posCtlPid", "zKp");
    haveZKp = PARAM_VARID_IS_VALID(idZKp);
    settling = false;
    settleStart = 0u;
    memset(&trace, 0, sizeof trace);
    psiFresh = false;
    polycc_swarm_reset(&swarm); /* swarm */
    pSwarmV = POLYCC_APP_DEFAULT_SWARM_V;
    lNbr = 0u;
    swarmTick = xTaskGetTickCount();
    swarmPeriodMs = 1u;
    pSwarmN = 0u;
    pSwarmId = 0u;
    pP2pMs = POLYCC_APP_DEFAULT_P2P_MS;
    pP2pAgeMs = POLYCC_APP_DEFAULT_P2P_AGE_MS;
    lastP2pTx = swarmTick;
    lP2pRx = 0u;
    lP2pTx = 0u;
    lP2pDrop = 0u;
    p2pTail = p2pHead; /* records heard before init are dropped */
    p2pRejected = 0u;
    p2pRegisterCB(onP2p);
    (void)periodTicks(pRateHz);
    polycc_controller_init(); /* shield (polycc_controller.c): off, defaults */
}

/* ---- shield hooks (polycc_controller.h) ---- */
const polycc_scene_t *polycc_app_scene(void)
{
    return &polycc_scene;
}

uint32_t polycc_app_scene_worst_cycles(void)
{
    return (uint32_t)POLYCC_SCENE_WORST_CYCLES;
}

float polycc_app_scene_kappa(void)
{
    return POLYCC_SCENE_KAPPA;
}

const polycc_app_trace_t *polycc_app_trace(void)
{
    return &trace;
}

/* Braking term: the largest speed from which the vehicle stops within the clearance psi of
 * the previous tick, assuming it reacts after POLYCC_APP_BRAKE_S and then decelerates at
 * POLYCC_APP_BRAKE_ACC: t s + s^2 / (2 A) = psi, s = A (sqrt(t^2 + 2 psi / A) - t).  Returns
 * vmax when braking is off, and at least POLYCC_APP_BRAKE_VMIN.  Without a psi from the previous
 * tick (the first tick of an engagement, or after a tick that held without evaluating) it returns
 * POLYCC_APP_BRAKE_VMIN: the vehicle may be anywhere since then.  Regression: it returned vmax, and the
 * first command of every flight was the unbraked go-to-goal velocity (1.5 m/s from a start 6 cm from a
 * box at vmax 2 m/s) for one tick; the shield, which flies each decision for one 10 ms period, flew it
 * and gave the vehicle a 110-145 m/s^3 jolt (bench/bench_shield.py). */
static float brakeSpeed(float vmax, bool fresh)
{
    const float t = POLYCC_APP_BRAKE_S, A = POLYCC_APP_BRAKE_ACC;
    float psi = trace.out.psi, s;
    if (!(A > 0.0f)) {
        return vmax;
    }
    if (!fresh || trace.calls == 0u || (trace.out.flags & POLYCC_FLAG_INVALID)) {
        return POLYCC_APP_BRAKE_VMIN < vmax ? POLYCC_APP_BRAKE_VMIN : vmax;
    }
    s = psi > 0.0f ? A * (sqrtf(t * t + 2.0f * psi / A) - t) : 0.0f;
    if (!(s > POLYCC_APP_BRAKE_VMIN)) {
        s = POLYCC_APP_BRAKE_VMIN;
    }
    return s < vmax ? s : vmax;
}

/* The radius the filter flies with this tick (POLYCC_APP_KEEPOUT_SLACK): polycc.radius, rising towards the
 * shield's keep-out as the previous tick's clearance allows.  fresh: the previous tick evaluated the kernel at
 * lRadius, so trace.out.psi + lRadius is its clearance. */
static float flightRadius(bool fresh)
{
    float keep = polycc_controller_keepout();
    float target = pRadius > keep ? pRadius : keep;
    float r = pRadius;
    if (fresh) {
        float room = (trace.out.psi + lRadius) - POLYCC_APP_KEEPOUT_SLACK;
        r = lRadius;
        if (room > r) { /* (a NaN room is not taken) */
            r = room;
        }
        if (r > target) {
            r = target;
        }
        if (r < pRadius) {
            r = pRadius;
        }
    }
    lRadius = r;
    return r;
}

/* Why the app may not take control now (POLYCC_STATUS_OK if it may). */
static uint8_t mayTakeControl(void)
{
    if (tooSlow()) {
        return POLYCC_STATUS_TOO_SLOW;
    }
    if (supervisorIsLocked() || supervisorIsCrashed() || supervisorIsTumbled()) {
        return POLYCC_STATUS_SUPERVISOR;
    }
    if (!runsPid()) {
        return POLYCC_STATUS_BAD_CONTROLLER;
    }
    if (engaged) {
        return POLYCC_STATUS_OK;
    }
    /* on the ground, or motors off (e.g. just landed: the supervisor's flying flag lags 2 s) */
    if (!supervisorIsFlying() || (haveThrust && !(logGetFloat(idThrust) > 0.0f))) {
        return POLYCC_STATUS_NOT_FLYING;
    }
    if (!crtpCommanderHighLevelIsStopped() && !crtpCommanderHighLevelIsTrajectoryFinished()) {
        return POLYCC_STATUS_WAIT_HL;
    }
    return POLYCC_STATUS_OK;
}

static void idle(uint8_t status)
{
    lStatus = status;
    lActive = 0u;
    lUx = 0.0f;
    lUy = 0.0f;
    lUz = 0.0f;
    sameTicks = 0u;
}

uint32_t polycc_app_tick(void)
{
    polycc_params_t prm;
    polycc_out_t out;
    float x[3], goal[3];
    uint64_t t0, t1;
    uint8_t status;
    uint32_t period = periodTicks(pRateHz);
    bool fresh = psiFresh;

    psiFresh = false; /* set again below if this tick evaluates the kernel */

    { /* swarm: age the neighbour reports by the time since the last tick (1 tick = 1 ms) */
        uint32_t now = xTaskGetTickCount();
        polycc_swarm_age(&swarm, (now - swarmTick) * (1000u / configTICK_RATE_HZ));
        swarmTick = now;
        swarmPeriodMs = period * (1000u / configTICK_RATE_HZ);
    }
    serviceAppChannel();
    if (haveEstimate) { /* swarm: neighbours heard over P2P, and the own broadcast */
        float xe[3];
        readVector(idX, idY, idZ, true, xe);
        drainP2p(xe);
        broadcastP2p(xe);
    }
    polycc_controller_plan((uint32_t)xTaskGetTickCount()); /* shield (polycc_controller.c): a decision when due */
    if (pEnable == 0u) {
        if (engaged) {
            handOverHold();
        }
        if (!engaged) {
            idle(linkLostLatched ? POLYCC_STATUS_LINK_LOST : POLYCC_STATUS_DISABLED);
            /* idle: no kernel call here, so the shield's 100 Hz planning sets the pace */
            return period > POLYCC_SHIELD_PERIOD_TICKS ? POLYCC_SHIELD_PERIOD_TICKS : period;
        }
        if (settling) { /* handOverHold sent the settling hold */
            lStatus = POLYCC_STATUS_HANDING_OVER;
            lActive = 0u;
            return period;
        }
        lStatus = POLYCC_STATUS_DISABLED; /* the high-level commander refused: handOverHold sent the hold */
        return period;
    }
    linkLostLatched = false;
    settling = false; /* enabled again during a settling hand-over: the app flies on */
    status = mayTakeControl();
    if (status == POLYCC_STATUS_SUPERVISOR) {
        if (engaged) { /* the supervisor stops the motors itself; hand the priority back */
            commanderRelaxPriority();
            engaged = false;
            settling = false;
        }
        idle(status);
        return period;
    }
    if (status != POLYCC_STATUS_OK) {
        if (engaged) {
            handOverHold();
        }
        idle(status);
        return period;
    }
    if (linkLost()) {
        if (engaged) {
            handOverLand();
            linkLostLatched = !engaged;
        }
        idle(POLYCC_STATUS_LINK_LOST);
        return period;
    }

    prm.kappa = POLYCC_SCENE_KAPPA;
    prm.radius = flightRadius(fresh);
    prm.beta = pBeta;
    prm.c_clf = pClfGain;
    prm.v_max = pVmax;
    goal[0] = pGoalX;
    goal[1] = pGoalY;
    goal[2] = pGoalZ;

    status = readEstimate(x, period);
    if (status != POLYCC_STATUS_OK) {
        lActive = 0u;
        lStatus = status;
        holdPosition(status == POLYCC_STATUS_STALE_ESTIMATE ? x : 0);
        return period;
    }
    memcpy(lastGood, x, sizeof lastGood);
    haveLastGood = true;
    if (polycc_swarm_stale(&swarm, POLYCC_SWARM_TIMEOUT_MS) || swarm.count < pSwarmN) { /* swarm: a neighbour
                                                                  fell silent, or one is not heard at all */
        lActive = 0u;
        lStatus = POLYCC_STATUS_NEIGHBOUR_LOST;
        holdPosition(x);
        return period;
    }

    prm.v_max = brakeSpeed(pVmax, fresh);

    t0 = usecTimestamp();
    (void)polycc_swarm_step(&polycc_scene, &prm, &swarm, pSwarmV, x, goal, &out); /* polycc_step without neighbours */
    t1 = usecTimestamp();
    lEvalUs = (uint32_t)(t1 - t0);
    lActive = (out.flags & POLYCC_FLAG_ACTIVE) ? 1u : 0u;
    trace.calls += 1u;
    memcpy(trace.x, x, sizeof trace.x);
    memcpy(trace.goal, goal, sizeof trace.goal);
    trace.params = prm;
    trace.out = out;
    psiFresh = true;
    lPsi = out.psi;

    if (out.flags & POLYCC_FLAG_INVALID) {
        lStatus = POLYCC_STATUS_KERNEL_INVALID;
        lActive = 0u;
        holdPosition(x);
    } else if (out.flags & POLYCC_FLAG_INSIDE) {
        lStatus = POLYCC_STATUS_INSIDE;
        lActive = 0u;
        holdPosition(x);
    } else {
        lStatus = POLYCC_STATUS_OK;
        sendVelocity(out.u[0], out.u[1], out.u[2]);
    }
    return period;
}

void appMain(void)
{
    TickType_t lastWake;
    polycc_app_init();
    DEBUG_PRINT("polycc: %u polytopes, %u half-planes, worst case %u cycles, %u Hz; set polycc.enable=1 in the air\n",
                (unsigned)POLYCC_SCENE_N_POLYS, (unsigned)POLYCC_SCENE_N_PLANES, (unsigned)POLYCC_SCENE_WORST_CYCLES,
                (unsigned)lRate);
    lastWake = xTaskGetTickCount();
    for (;;) {
        TickType_t period = (TickType_t)polycc_app_tick();
        vTaskDelayUntil(&lastWake, period);
        if ((TickType_t)(xTaskGetTickCount() - lastWake) > 1u) {
            ++lLate; /* woke late: higher-priority work, an overrun, or (SITL) a starved host */
        }
    }
}

/**
 * polycc safety filter.  Lengths in metres, speeds in m/s, world frame.
 */
PARAM_GROUP_START(polycc)
/** @brief Nonzero: fly to the goal through the filter once flying and the high-level commander is done; 0 hands
 * the vehicle back to the high-level commander holding position (default 0) */
PARAM_ADD(PARAM_UINT8, enable, &pEnable)
/** @brief Goal x, m (default 0) */
PARAM_ADD(PARAM_FLOAT, goalX, &pGoalX)
/** @brief Goal y, m (default 0) */
PARAM_ADD(PARAM_FLOAT, goalY, &pGoalY)
/** @brief Goal z, m (default 1) */
PARAM_ADD(PARAM_FLOAT, goalZ, &pGoalZ)
/** @brief Speed limit, m/s; the braking term lowers it near obstacles (default 0.5) */
PARAM_ADD(PARAM_FLOAT, vmax, &pVmax)
/** @brief CBF class-K gain beta, 1/s (default 1) */
PARAM_ADD(PARAM_FLOAT, beta, &pBeta)
/** @brief CLF decay rate c, 1/s: u_nom = -(c/2)(x - goal) (default 2) */
PARAM_ADD(PARAM_FLOAT, clfGain, &pClfGain)
/** @brief Agent radius r, m (default 0.1) */
PARAM_ADD(PARAM_FLOAT, radius, &pRadius)
/** @brief Requested loop rate, Hz (10..1000, whole 1 ms ticks, lowered until the scene's worst case fits;
 * log polycc.rate is the rate used; default 500) */
PARAM_ADD(PARAM_UINT16, rateHz, &pRateHz)
/** @brief Swarm: the neighbours' speed bound V, m/s; stale reports enlarge the buffer by V x age (default 1) */
PARAM_ADD(PARAM_FLOAT, swarmV, &pSwarmV)
/** @brief Swarm: the number of neighbours this drone must know before it moves; fewer: hold (status 13)
 * (default 0) */
PARAM_ADD(PARAM_UINT8, swarmN, &pSwarmN)
/** @brief Swarm: own id in P2P broadcasts, 1-255; 0: broadcast nothing (records heard are still used)
 * (default 0) */
PARAM_ADD(PARAM_UINT8, swarmId, &pSwarmId)
/** @brief Swarm: period of the own P2P broadcast, ms; 0: none (default 50) */
PARAM_ADD(PARAM_UINT16, p2pMs, &pP2pMs)
/** @brief Swarm: age stated in the own P2P broadcasts, ms: own estimate error / swarmV + radio latency bound
 * (default 20) */
PARAM_ADD(PARAM_UINT16, p2pAgeMs, &pP2pAgeMs)
PARAM_GROUP_STOP(polycc)

/**
 * polycc safety filter state.
 */
LOG_GROUP_START(polycc)
/** @brief Certified barrier psi at the estimate, m (>= 0: the agent ball is clear) */
LOG_ADD(LOG_FLOAT, psi, &lPsi)
/** @brief Commanded world-frame velocity x, m/s (0 while holding) */
LOG_ADD(LOG_FLOAT, ux, &lUx)
/** @brief Commanded world-frame velocity y, m/s */
LOG_ADD(LOG_FLOAT, uy, &lUy)
/** @brief Commanded world-frame velocity z, m/s */
LOG_ADD(LOG_FLOAT, uz, &lUz)
/** @brief 1 when the CBF filter changed the nominal command */
LOG_ADD(LOG_UINT8, active, &lActive)
/** @brief Time of one kernel evaluation, us (usecTimestamp) */
LOG_ADD(LOG_UINT32, evalUs, &lEvalUs)
/** @brief 0 disabled, 1 ok (engaged), 2 no estimate, 3 bad estimate, 4 stale estimate, 5 inside an obstacle,
 * 6 kernel invalid (2-6 hold position), 7 not flying (take off first), 8 waiting for the high-level commander,
 * 9 controller is not PID, 10 link lost (landing), 11 supervisor locked/crashed/tumbled, 12 scene too slow,
 * 13 a neighbour fell silent (holding), 14 disabled, holding until the position controller has settled before the
 * hand-over */
LOG_ADD(LOG_UINT8, status, &lStatus)
/** @brief Loop rate in use, Hz (rateHz, lowered until the scene's certified worst case fits half a tick) */
LOG_ADD(LOG_UINT16, rate, &lRate)
/** @brief App ticks since boot that started more than one RTOS tick after their scheduled time (0 on an idle
 * vehicle; in SITL, a host that starves the firmware) */
LOG_ADD(LOG_UINT32, late, &lLate)
/** @brief Swarm: neighbours in the table (reports received over the app channel) */
LOG_ADD(LOG_UINT8, nNbr, &lNbr)
/** @brief Swarm: P2P neighbour records taken into the table (wraps) */
LOG_ADD(LOG_UINT16, p2pRx, &lP2pRx)
/** @brief Swarm: own P2P broadcasts sent (wraps) */
LOG_ADD(LOG_UINT16, p2pTx, &lP2pTx)
/** @brief Swarm: P2P records refused: malformed, ring full, own id, "forget", table full (wraps) */
LOG_ADD(LOG_UINT16, p2pDrop, &lP2pDrop)
/** @brief Radius the filter flies with, m: polycc.radius, rising to polyccShield.radius + tube while the shield
 * is on and the clearance allows */
LOG_ADD(LOG_FLOAT, radius, &lRadius)
LOG_GROUP_STOP(polycc)
