/*
 * polycc_app.c -- Crazyflie app layer: certified polytope CBF safety filter around a CLF
 * go-to-goal controller, flying world-frame velocity setpoints.
 *
 * The only polycc C file that includes firmware headers.  The host SITL compiles this very
 * file against declaration shims (polycc/sim/shims/) with the same flags.
 *
 * Each tick (polycc_app_tick, at param polycc.rateHz, default 500 Hz):
 *   1. reads stateEstimate.x/y/z through the log API (and kalman.varX/Y/Z when present);
 *   2. runs polycc_step() of the kernel on the generated scene (polytopes.h), with the speed
 *      limit lowered near obstacles by the braking term (polycc_app.h, POLYCC_APP_BRAKE_*);
 *   3. sends a world-frame velocity setpoint with commanderSetSetpoint, every tick while
 *      enabled (so the commander's 500 ms / 2 s watchdog never fires);
 *   a bad or stale estimate, psi < 0 or a kernel refusal sends zero velocity (hover in place)
 *   and sets polycc.status; disabling relaxes the commander priority once.
 *
 * Build: -ffp-contract=off (bit-exact kernel) and -fno-math-errno; see src/Kbuild.
 */
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "app.h"
#include "commander.h"
#include "FreeRTOS.h"
#include "log.h"
#include "param.h"
#include "task.h"
#include "usec_time.h"

#define DEBUG_MODULE "POLYCC"
#include "debug.h"

#include "polycc_app.h"
#include "polycc_kernel.h"

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

/* Commander priority of the app's setpoints: above the high-level commander, equal to CRTP
 * setpoints from a ground station (the newest wins), below an external receiver. */
#ifndef POLYCC_APP_PRIORITY
#define POLYCC_APP_PRIORITY COMMANDER_PRIORITY_CRTP
#endif

/* ---- parameter group polycc (written by the param task; snapshotted once per tick) ---- */
static uint8_t pEnable;
static float pGoalX, pGoalY, pGoalZ;
static float pVmax, pBeta, pClfGain, pRadius;
static uint16_t pRateHz;

/* ---- log group polycc ---- */
static float lPsi, lUx, lUy, lUz;
static uint8_t lActive, lStatus;
static uint32_t lEvalUs;

/* ---- state ---- */
static logVarId_t idX, idY, idZ, idVarX, idVarY, idVarZ;
static bool haveEstimate, haveVariance, wasEnabled;
static polycc_app_trace_t trace;
static uint32_t lastBits[3];
static uint32_t sameTicks; /* ms for which the estimate bits did not change */
static setpoint_t setpoint;

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

/* rateHz clamped to [POLYCC_APP_MIN_RATE_HZ, tick rate], rounded to whole ticks. */
static uint32_t periodTicks(uint16_t rateHz)
{
    uint32_t r = rateHz < POLYCC_APP_MIN_RATE_HZ ? POLYCC_APP_MIN_RATE_HZ : rateHz;
    uint32_t t = (configTICK_RATE_HZ + r / 2u) / r;
    return t < 1u ? 1u : t;
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
    commanderSetSetpoint(&setpoint, POLYCC_APP_PRIORITY);
    lUx = vx;
    lUy = vy;
    lUz = vz;
}

/* Estimate check; returns POLYCC_STATUS_OK or the reason to hover. */
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
    lUx = 0.0f;
    lUy = 0.0f;
    lUz = 0.0f;
    lActive = 0u;
    lStatus = POLYCC_STATUS_DISABLED;
    lEvalUs = 0u;
    wasEnabled = false;
    sameTicks = 0u;
    lastBits[0] = 0xffffffffu; /* a NaN pattern the estimate never starts with */
    lastBits[1] = 0xffffffffu;
    lastBits[2] = 0xffffffffu;
    idX = logGetVarId("stateEstimate", "x");
    idY = logGetVarId("stateEstimate", "y");
    idZ = logGetVarId("stateEstimate", "z");
    idVarX = logGetVarId("kalman", "varX");
    idVarY = logGetVarId("kalman", "varY");
    idVarZ = logGetVarId("kalman", "varZ");
    haveEstimate = logVarIdIsValid(idX) && logVarIdIsValid(idY) && logVarIdIsValid(idZ);
    haveVariance = logVarIdIsValid(idVarX) && logVarIdIsValid(idVarY) && logVarIdIsValid(idVarZ);
    memset(&trace, 0, sizeof trace);
}

const polycc_app_trace_t *polycc_app_trace(void)
{
    return &trace;
}

/* Braking term: the largest speed from which the vehicle stops within the clearance psi of
 * the previous tick, assuming it reacts after POLYCC_APP_BRAKE_S and then decelerates at
 * POLYCC_APP_BRAKE_ACC: t s + s^2 / (2 A) = psi, s = A (sqrt(t^2 + 2 psi / A) - t).  Returns
 * vmax when braking is off or no previous evaluation exists, and at least POLYCC_APP_BRAKE_VMIN. */
static float brakeSpeed(float vmax)
{
    const float t = POLYCC_APP_BRAKE_S, A = POLYCC_APP_BRAKE_ACC;
    float psi = trace.out.psi, s;
    if (!(A > 0.0f) || trace.calls == 0u || (trace.out.flags & POLYCC_FLAG_INVALID)) {
        return vmax;
    }
    s = psi > 0.0f ? A * (sqrtf(t * t + 2.0f * psi / A) - t) : 0.0f;
    if (!(s > POLYCC_APP_BRAKE_VMIN)) {
        s = POLYCC_APP_BRAKE_VMIN;
    }
    return s < vmax ? s : vmax;
}

uint32_t polycc_app_tick(void)
{
    polycc_params_t prm;
    polycc_out_t out;
    float x[3], goal[3];
    uint64_t t0, t1;
    uint8_t status;
    uint32_t period = periodTicks(pRateHz);

    if (pEnable == 0u) {
        if (wasEnabled) {
            commanderRelaxPriority();
            wasEnabled = false;
        }
        lStatus = POLYCC_STATUS_DISABLED;
        lActive = 0u;
        lUx = 0.0f;
        lUy = 0.0f;
        lUz = 0.0f;
        sameTicks = 0u;
        return period;
    }
    wasEnabled = true;

    prm.kappa = POLYCC_SCENE_KAPPA;
    prm.radius = pRadius;
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
        sendVelocity(0.0f, 0.0f, 0.0f);
        return period;
    }

    prm.v_max = brakeSpeed(pVmax);

    t0 = usecTimestamp();
    (void)polycc_step(&polycc_scene, &prm, x, goal, &out);
    t1 = usecTimestamp();
    lEvalUs = (uint32_t)(t1 - t0);
    lActive = (out.flags & POLYCC_FLAG_ACTIVE) ? 1u : 0u;
    trace.calls += 1u;
    memcpy(trace.x, x, sizeof trace.x);
    memcpy(trace.goal, goal, sizeof trace.goal);
    trace.params = prm;
    trace.out = out;
    lPsi = out.psi;

    if (out.flags & POLYCC_FLAG_INVALID) {
        lStatus = POLYCC_STATUS_KERNEL_INVALID;
        lActive = 0u;
        sendVelocity(0.0f, 0.0f, 0.0f);
    } else if (out.flags & POLYCC_FLAG_INSIDE) {
        lStatus = POLYCC_STATUS_INSIDE;
        lActive = 0u;
        sendVelocity(0.0f, 0.0f, 0.0f);
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
    DEBUG_PRINT("polycc: %u polytopes, %u half-planes; set polycc.enable=1 to fly\n",
                (unsigned)POLYCC_SCENE_N_POLYS, (unsigned)POLYCC_SCENE_N_PLANES);
    lastWake = xTaskGetTickCount();
    for (;;) {
        TickType_t period = (TickType_t)polycc_app_tick();
        vTaskDelayUntil(&lastWake, period);
    }
}

/**
 * polycc safety filter.  Lengths in metres, speeds in m/s, world frame.
 */
PARAM_GROUP_START(polycc)
/** @brief Nonzero: fly to the goal through the filter (streams setpoints); 0 releases control (default 0) */
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
/** @brief Loop rate, Hz (10..1000; period rounded to whole 1 ms ticks; default 500) */
PARAM_ADD(PARAM_UINT16, rateHz, &pRateHz)
PARAM_GROUP_STOP(polycc)

/**
 * polycc safety filter state.
 */
LOG_GROUP_START(polycc)
/** @brief Certified barrier psi at the estimate, m (>= 0: the agent ball is clear) */
LOG_ADD(LOG_FLOAT, psi, &lPsi)
/** @brief Commanded world-frame velocity x, m/s */
LOG_ADD(LOG_FLOAT, ux, &lUx)
/** @brief Commanded world-frame velocity y, m/s */
LOG_ADD(LOG_FLOAT, uy, &lUy)
/** @brief Commanded world-frame velocity z, m/s */
LOG_ADD(LOG_FLOAT, uz, &lUz)
/** @brief 1 when the CBF filter changed the nominal command */
LOG_ADD(LOG_UINT8, active, &lActive)
/** @brief Time of one kernel evaluation, us (usecTimestamp) */
LOG_ADD(LOG_UINT32, evalUs, &lEvalUs)
/** @brief POLYCC_STATUS_* (polycc_app.h): 0 disabled, 1 ok, 2 no estimate, 3 bad estimate, 4 stale, 5 inside, 6 kernel invalid */
LOG_ADD(LOG_UINT8, status, &lStatus)
LOG_GROUP_STOP(polycc)
