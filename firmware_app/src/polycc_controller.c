/*
 * polycc_controller.c -- the shield mode: out-of-tree controller wrapping the firmware's PID, and
 * the per-tick filter that runs the shield on every setpoint (polycc_controller.h).
 *
 * Build: CONFIG_CONTROLLER_OOT=y (firmware_app/app-config) and stabilizer.controller set to the
 * out-of-tree controller; the app's scene comes from polycc_app.c (one copy in flash).
 * The host SITL compiles this file against the shims, whose stabilizer step calls
 * controllerOutOfTree() exactly as the firmware's stabilizer loop does.
 */
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "controller.h"
#include "controller_pid.h"
#include "log.h"
#include "param.h"
#include "stabilizer_types.h"

#define DEBUG_MODULE "POLYCCSH"
#include "debug.h"

#include "polycc_app.h"
#include "polycc_controller.h"
#include "polycc_shield.h"

#define G_MS2 9.81f

/* ---- parameter group polyccShield ---- */
static uint8_t pOn;
static float pTube = POLYCC_SHIELD_DEFAULT_TUBE, pVmax = POLYCC_SHIELD_DEFAULT_VMAX;
static float pK1 = POLYCC_SHIELD_DEFAULT_K1, pK0 = POLYCC_SHIELD_DEFAULT_K0;

/* ---- state ---- */
static polycc_shield_job_t job;
static polycc_shield_params_t jobPrm;
static bool on;            /* the shield filters setpoints */
static bool planning;      /* job belongs to the running period */
static bool haveDecision;  /* a decision is being flown */
static bool passThrough;   /* the decision lets the live setpoint through */
static bool warnedManual;
static float uCmd[3];      /* the decision's velocity */
static float uPlanned[3];  /* desired velocity the decision was planned for */
static polycc_controller_trace_t trace;

/* ---- log group polyccShield ---- */
static float lPsi, lMinC;

static float clampf(float x, float lo, float hi)
{
    return x < lo ? lo : (x > hi ? hi : x);
}

uint32_t polycc_controller_evals_per_tick(void)
{
    const uint32_t avail = (POLYCC_APP_CPU_HZ / 1000u) * POLYCC_SHIELD_TICK_SHARE_PERCENT / 100u;
    const uint32_t worst = polycc_app_scene_worst_cycles();
    uint32_t e;
    if (avail <= POLYCC_SHIELD_FIXED_CYCLES || worst == 0u) {
        return 0u;
    }
    e = (avail - POLYCC_SHIELD_FIXED_CYCLES) / worst;
    return e > POLYCC_SHIELD_MAX_EVALS ? POLYCC_SHIELD_MAX_EVALS : e;
}

static void fillParams(polycc_shield_params_t *q)
{
    uint32_t e = polycc_controller_evals_per_tick();
    uint32_t evals = 1u + e * (POLYCC_SHIELD_PERIOD_TICKS - 2u);
    q->kappa = polycc_app_scene_kappa();
    q->radius = polycc_app_radius();
    q->h = 0.01f;
    q->k_v = 4.2803f;  /* PID_VEL_X_KP 25 deg per m/s times g (polycc.sim.dynamics.CrazyflieParams) */
    q->k_z = 9.3f;
    q->a_xy = 3.96f;   /* g tan 22 deg */
    q->a_up = 11.77f;  /* 1.2 g */
    q->a_dn = 5.69f;   /* 0.58 g */
    q->tau = 1.0f / 6.0f;
    q->k1 = pK1;
    q->k0 = pK0;
    q->v_max = pVmax;
    q->tube = pTube;
    q->v_term = 0.05f;
    q->a_term = 0.5f;
    q->n_lat = 3u;   /* 20 ms estimator delay + the 10 ms until the decision is flown */
    q->n_commit = 1u;
    q->n_steps = POLYCC_SHIELD_MAX_STEPS;
    q->max_evals = evals > POLYCC_SHIELD_MAX_EVALS ? POLYCC_SHIELD_MAX_EVALS : evals;
}

/* Runtime state only (the parameters keep their values): also on every controller switch. */
static void resetState(void)
{
    on = false;
    planning = false;
    haveDecision = false;
    passThrough = false;
    warnedManual = false;
    memset(uCmd, 0, sizeof uCmd);
    memset(uPlanned, 0, sizeof uPlanned);
    memset(&trace, 0, sizeof trace);
    memset(&job, 0, sizeof job);
    lPsi = 0.0f;
    lMinC = 0.0f;
}

void polycc_controller_init(void)
{
    pOn = 0u;
    pTube = POLYCC_SHIELD_DEFAULT_TUBE;
    pVmax = POLYCC_SHIELD_DEFAULT_VMAX;
    pK1 = POLYCC_SHIELD_DEFAULT_K1;
    pK0 = POLYCC_SHIELD_DEFAULT_K0;
    resetState();
}

const polycc_controller_trace_t *polycc_controller_trace(void)
{
    return &trace;
}

/* The velocity the PID cascade aims for under sp (world frame); false for manual setpoints. */
static bool desiredVelocity(const setpoint_t *sp, const float pos[3], float yaw_deg, float u[3])
{
    const stab_mode_t m[3] = {sp->mode.x, sp->mode.y, sp->mode.z};
    float sv[3] = {sp->velocity.x, sp->velocity.y, sp->velocity.z};
    const float spp[3] = {sp->position.x, sp->position.y, sp->position.z};
    int i;
    if (m[0] == modeDisable || m[1] == modeDisable || m[2] == modeDisable) {
        return false;
    }
    if (sp->velocity_body) {
        float yaw = yaw_deg * (3.14159265358979f / 180.0f), c = cosf(yaw), s = sinf(yaw);
        float bx = sv[0], by = sv[1];
        sv[0] = c * bx - s * by;
        sv[1] = s * bx + c * by;
    }
    for (i = 0; i < 3; ++i) {
        u[i] = m[i] == modeAbs ? clampf(sv[i] + POLYCC_SHIELD_POS_KP * (spp[i] - pos[i]), -POLYCC_SHIELD_POS_VMAX,
                                        POLYCC_SHIELD_POS_VMAX)
                               : sv[i];
    }
    return true;
}

static void override(setpoint_t *sp, const float u[3])
{
    sp->mode.x = modeVelocity;
    sp->mode.y = modeVelocity;
    sp->mode.z = modeVelocity;
    sp->velocity.x = u[0];
    sp->velocity.y = u[1];
    sp->velocity.z = u[2];
    sp->velocity_body = false;
    sp->acceleration.x = 0.0f;
    sp->acceleration.y = 0.0f;
    sp->acceleration.z = 0.0f;
    trace.overrides += 1u;
}

/* The finished plan of the last period becomes the decision flown now. */
static void decide(void)
{
    uint32_t f = job.flags;
    if (!planning) {
        return;
    }
    planning = false;
    if (!(f & POLYCC_SHIELD_DONE)) { /* out of ticks: not certified */
        f |= POLYCC_SHIELD_EVAL_CAP | POLYCC_SHIELD_DONE;
    }
    trace.decisions += 1u;
    trace.last_flags = f;
    trace.last_evals = job.evals;
    trace.last_min_c = job.min_c;
    trace.psi = job.psi;
    lPsi = job.psi;
    lMinC = job.min_c;
    if (f & POLYCC_SHIELD_INFEASIBLE) {
        trace.infeasible += 1u;
    }
    if (f & POLYCC_SHIELD_EVAL_CAP) {
        trace.eval_caps += 1u;
    }
    haveDecision = true;
    if (f & POLYCC_SHIELD_CERTIFIED) {
        trace.certified += 1u;
        memcpy(uCmd, job.u_c, sizeof uCmd);
        passThrough = !(f & (POLYCC_SHIELD_ACTIVE | POLYCC_SHIELD_SATURATED));
        trace.status = passThrough ? POLYCC_SHIELD_STATUS_PASS : POLYCC_SHIELD_STATUS_FILTERED;
    } else {
        trace.backups += 1u;
        memset(uCmd, 0, sizeof uCmd);
        passThrough = false;
        trace.status = POLYCC_SHIELD_STATUS_BACKUP;
    }
    memcpy(trace.u, uCmd, sizeof uCmd);
}

static void switchOff(void)
{
    on = false;
    planning = false;
    haveDecision = false;
    passThrough = false;
    trace.status = POLYCC_SHIELD_STATUS_OFF;
}

void polycc_controller_filter(setpoint_t *sp, const float pos[3], const float vel[3], const float acc[3],
                              float yaw_deg, uint32_t tick)
{
    const uint32_t phase = tick % POLYCC_SHIELD_PERIOD_TICKS;
    float ud[3];
    bool manual;
    trace.on = on ? 1u : 0u;
    if (!on && !pOn) {
        trace.status = POLYCC_SHIELD_STATUS_OFF;
        return;
    }
    if (polycc_controller_evals_per_tick() == 0u) {
        if (trace.status != POLYCC_SHIELD_STATUS_TOO_SLOW) {
            DEBUG_PRINT("shield refused: the scene's worst case (%u cycles) does not fit a stabilizer tick\n",
                        (unsigned)polycc_app_scene_worst_cycles());
        }
        switchOff();
        trace.status = POLYCC_SHIELD_STATUS_TOO_SLOW;
        return;
    }
    manual = !desiredVelocity(sp, pos, yaw_deg, ud);
    if (phase == 0u) {
        float speed2 = (vel[0] * vel[0] + vel[1] * vel[1]) + vel[2] * vel[2];
        if (on) {
            decide();
        }
        if (!pOn && on) { /* safe hand-over: only while the shield leaves the setpoint alone, or at rest */
            if (!haveDecision || passThrough || speed2 <= 0.05f * 0.05f || manual) {
                switchOff();
                return;
            }
        }
        if (pOn && !on) {
            on = true;
            haveDecision = false;
            warnedManual = false;
        }
        if (!manual) {
            const float *uApp = haveDecision && !passThrough ? uCmd : ud;
            fillParams(&jobPrm);
            (void)polycc_shield_begin(&job, polycc_app_scene(), &jobPrm, pos, vel, acc, uApp, ud);
            memcpy(uPlanned, ud, sizeof uPlanned);
            planning = true;
        }
    } else if (planning && phase == 1u) {
        (void)polycc_shield_simulate(&job, &jobPrm);
    } else if (planning) {
        uint32_t k, e = polycc_controller_evals_per_tick();
        for (k = 0u; k < e && !(job.flags & POLYCC_SHIELD_DONE); ++k) {
            (void)polycc_shield_advance(&job, polycc_app_scene(), &jobPrm);
        }
    }
    trace.on = 1u;
    if (manual) {
        if (!warnedManual) {
            DEBUG_PRINT("shield: manual attitude/rate setpoint passed unfiltered (not protected)\n");
            warnedManual = true;
        }
        trace.manual += 1u;
        trace.status = POLYCC_SHIELD_STATUS_MANUAL;
        haveDecision = false;
        return;
    }
    if (!haveDecision) {
        trace.status = POLYCC_SHIELD_STATUS_STARTING;
        return;
    }
    if (!pOn) {
        trace.status = POLYCC_SHIELD_STATUS_OFF_PENDING;
    }
    if (passThrough && fabsf(ud[0] - uPlanned[0]) <= POLYCC_SHIELD_PASS_TOL &&
        fabsf(ud[1] - uPlanned[1]) <= POLYCC_SHIELD_PASS_TOL && fabsf(ud[2] - uPlanned[2]) <= POLYCC_SHIELD_PASS_TOL) {
        return;
    }
    override(sp, passThrough ? uPlanned : uCmd);
}

#ifdef CONFIG_CONTROLLER_OOT
/* ---- the out-of-tree controller: the shield, then the firmware's PID ---- */
void controllerOutOfTreeInit(void)
{
    controllerPidInit();
    resetState();
}

bool controllerOutOfTreeTest(void)
{
    return controllerPidTest();
}

void controllerOutOfTree(control_t *control, const setpoint_t *setpoint, const sensorData_t *sensors,
                         const state_t *state, const stabilizerStep_t stabilizerStep)
{
    setpoint_t sp = *setpoint;
    const float pos[3] = {state->position.x, state->position.y, state->position.z};
    const float vel[3] = {state->velocity.x, state->velocity.y, state->velocity.z};
    const float acc[3] = {state->acc.x * G_MS2, state->acc.y * G_MS2, state->acc.z * G_MS2};
    polycc_controller_filter(&sp, pos, vel, acc, state->attitude.yaw, (uint32_t)stabilizerStep);
    controllerPid(control, &sp, sensors, state, stabilizerStep);
}
#endif

/**
 * polycc shield: every position/velocity setpoint through the certified barrier (docs/barrier.md 8).
 */
PARAM_GROUP_START(polyccShield)
/** @brief Nonzero: filter every setpoint (needs stabilizer.controller = out-of-tree); 0: off, after a safe
 * hand-over (default 0) */
PARAM_ADD(PARAM_UINT8, enable, &pOn)
/** @brief Model-tracking allowance e_tube, m (default 0.05) */
PARAM_ADD(PARAM_FLOAT, tube, &pTube)
/** @brief Speed cap of the filtered command, m/s (default 3) */
PARAM_ADD(PARAM_FLOAT, vmax, &pVmax)
/** @brief ECBF gain on the barrier rate, 1/s (default 4) */
PARAM_ADD(PARAM_FLOAT, k1, &pK1)
/** @brief ECBF gain on the barrier, 1/s^2 (default 4) */
PARAM_ADD(PARAM_FLOAT, k0, &pK0)
PARAM_GROUP_STOP(polyccShield)

/**
 * polycc shield state.
 */
LOG_GROUP_START(polyccShield)
/** @brief 0 off, 1 pass, 2 filtered, 3 backup (braking), 4 manual (unfiltered), 5 off pending, 6 too slow, 7 starting */
LOG_ADD(LOG_UINT8, status, &trace.status)
/** @brief Decisions made (100 Hz while on) */
LOG_ADD(LOG_UINT32, decisions, &trace.decisions)
/** @brief Decisions that flew the backup (brake to hover) */
LOG_ADD(LOG_UINT32, backups, &trace.backups)
/** @brief ECBF candidates infeasible within vmax */
LOG_ADD(LOG_UINT32, infeasible, &trace.infeasible)
/** @brief Ticks with a manual setpoint passed unfiltered */
LOG_ADD(LOG_UINT32, manual, &trace.manual)
/** @brief psi at the last decision's estimate, m */
LOG_ADD(LOG_FLOAT, psi, &lPsi)
/** @brief Smallest psi - tube over the last plan's samples, m */
LOG_ADD(LOG_FLOAT, minC, &lMinC)
/** @brief Commanded velocity x of the decision, m/s */
LOG_ADD(LOG_FLOAT, ux, &trace.u[0])
/** @brief Commanded velocity y, m/s */
LOG_ADD(LOG_FLOAT, uy, &trace.u[1])
/** @brief Commanded velocity z, m/s */
LOG_ADD(LOG_FLOAT, uz, &trace.u[2])
LOG_GROUP_STOP(polyccShield)
