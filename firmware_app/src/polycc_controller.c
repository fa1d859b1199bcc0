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

/* The firmware's Kconfig symbols (CONFIG_CONTROLLER_OOT) before controller.h reads them: the
 * firmware force-includes nothing for an out-of-tree app, and debug.h pulls autoconf.h in too late. */
#if defined(__has_include)
#if __has_include("autoconf.h")
#include "autoconf.h"
#endif
#endif
#include "controller.h"
#include "controller_pid.h"
#include "FreeRTOS.h"
#include "log.h"
#include "param.h"
#include "stabilizer_types.h"
#include "task.h"

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
static float pRadius = POLYCC_SHIELD_DEFAULT_RADIUS;
static float pPsiCap = POLYCC_SHIELD_DEFAULT_PSI_CAP;

/* ---- stabilizer -> app: the latest setpoint and estimate (under taskENTER_CRITICAL) ---- */
typedef struct mailbox {
    float pos[3], vel[3], acc[3], ud[3];
    float sv[3];  /* the setpoint's own velocity (feed-forward), world frame, m/s */
    float gap2; /* squared horizontal distance, m^2, from a position setpoint to the estimate (0: none) */
    uint32_t tick;
    bool manual, valid;
} mailbox_t;

/* ---- app -> stabilizer: decisions ---- */
typedef struct decision {
    float u[3];        /* velocity flown when not passing */
    float planned[3];  /* desired velocity it was planned for */
    uint32_t from, to; /* flown for from <= tick < to (stabilizer ticks) */
    bool pass;         /* the live setpoint passes while it stays near `planned` */
    bool brake;        /* the backup: the brake policy at the live estimate (polycc_shield_brake) */
    bool land;         /* a landing: hold x, y at `at`, the source's z (u[2]: its desired vz, capped) */
    float at[2];       /* where the landing began, m */
    bool valid;
} decision_t;

static mailbox_t mbox;
static decision_t cur, next;
static volatile bool on; /* the shield filters setpoints (written by the app task) */
static bool warnedManual, warnedSlow;
static bool holding; /* the backup holds position at holdAt (stabilizer side) */
static float holdAt[3];
static uint32_t lastPlan;
static bool planned;
static polycc_shield_job_t job; /* 4 kB: one plan */
static polycc_shield_params_t jobPrm;
static polycc_controller_trace_t trace;
static float lPsi, lMinC;

static float clampf(float x, float lo, float hi)
{
    return x < lo ? lo : (x > hi ? hi : x);
}

uint32_t polycc_controller_max_evals(void)
{
    const uint64_t avail = (uint64_t)(POLYCC_APP_CPU_HZ / 1000u) * POLYCC_SHIELD_PERIOD_TICKS *
                           POLYCC_SHIELD_CPU_SHARE_PERCENT / 100u;
    const uint64_t own = POLYCC_SHIELD_FIXED_CYCLES + (uint64_t)POLYCC_SHIELD_STEP_CYCLES * POLYCC_SHIELD_MAX_STEPS;
    const uint64_t worst = polycc_app_scene_worst_cycles();
    uint64_t e;
    if (avail <= own || worst == 0u) {
        return 0u;
    }
    e = (avail - own) / worst;
    return e > POLYCC_SHIELD_MAX_EVALS ? POLYCC_SHIELD_MAX_EVALS : (uint32_t)e;
}

float polycc_controller_keepout(void)
{
    return pOn ? pRadius + pTube : 0.0f;
}

uint32_t polycc_controller_plan_worst_cycles(void)
{
    return POLYCC_SHIELD_FIXED_CYCLES + POLYCC_SHIELD_STEP_CYCLES * POLYCC_SHIELD_MAX_STEPS +
           polycc_controller_max_evals() * polycc_app_scene_worst_cycles();
}

static void fillParams(polycc_shield_params_t *q)
{
    q->kappa = polycc_app_scene_kappa();
    q->radius = pRadius;
    q->h = 0.01f;
    q->k_v = POLYCC_SHIELD_K_V; /* PID_VEL_X_KP 25 deg per m/s times g (polycc.sim.dynamics.CrazyflieParams) */
    q->k_z = 9.3f;
    q->a_xy = POLYCC_SHIELD_A_XY;
    q->a_up = 11.77f; /* 1.2 g */
    q->a_dn = 5.69f;  /* 0.58 g */
    q->tau = POLYCC_SHIELD_TAU; /* conservative: attitude loop 1/6 s plus rate loop and motor lag */
    q->k1 = pK1;
    q->k0 = pK0;
    q->v_max = pVmax;
    q->tube = pTube;
    q->v_term = 0.05f;
    q->a_term = 0.5f;
    q->psi_cap = pPsiCap;
    q->a_brake = POLYCC_SHIELD_A_BRAKE;
    q->n_lat = POLYCC_SHIELD_N_LAT;
    q->n_commit = POLYCC_SHIELD_N_COMMIT;
    q->n_steps = POLYCC_SHIELD_MAX_STEPS;
    q->max_evals = polycc_controller_max_evals();
}

/* Runtime state only (the parameters keep their values): also on every controller switch. */
static void resetState(void)
{
    memset(&mbox, 0, sizeof mbox);
    memset(&cur, 0, sizeof cur);
    memset(&next, 0, sizeof next);
    on = false;
    warnedManual = false;
    warnedSlow = false;
    holding = false;
    lastPlan = 0u;
    planned = false;
    memset(&trace, 0, sizeof trace);
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
    pRadius = POLYCC_SHIELD_DEFAULT_RADIUS;
    pPsiCap = POLYCC_SHIELD_DEFAULT_PSI_CAP;
    resetState();
}

const polycc_controller_trace_t *polycc_controller_trace(void)
{
    return &trace;
}

const polycc_shield_job_t *polycc_controller_job(void)
{
    return &job;
}

/* The velocity u the PID cascade aims for under sp (world frame), and sv the setpoint's own velocity (world
 * frame); false for manual setpoints.  Under a position setpoint the PID's position loop commands
 * kp (setpoint - estimate) + its integral output (z: zi, posCtl.Zi, m/s), limited, and does not feed the
 * setpoint's velocity forward (position_controller_pid.c): predicting it with the feed-forward or without the
 * integral made the shield expect motion the vehicle did not make (a hold 0.13 m below a vehicle whose
 * take-off had wound Zi up read as a 0.27 m/s descent; real-firmware SITL). */
static bool desiredVelocity(const setpoint_t *sp, const float pos[3], float yaw_deg, float zi, float u[3],
                            float sv[3])
{
    const stab_mode_t m[3] = {sp->mode.x, sp->mode.y, sp->mode.z};
    const float spp[3] = {sp->position.x, sp->position.y, sp->position.z};
    const float integ[3] = {0.0f, 0.0f, zi};
    int i;
    sv[0] = sp->velocity.x;
    sv[1] = sp->velocity.y;
    sv[2] = sp->velocity.z;
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
        u[i] = m[i] == modeAbs ? clampf(POLYCC_SHIELD_POS_KP * (spp[i] - pos[i]) + integ[i], -POLYCC_SHIELD_POS_VMAX,
                                        POLYCC_SHIELD_POS_VMAX)
                               : sv[i];
    }
    return true;
}

/* The commanded brake's velocity error bound e = a_xy / k_v, m/s: the strongest brake that stays inside
 * the tilt limits in every direction (the model assumes only a_brake of it). */
static float brakeErr(void)
{
    return POLYCC_SHIELD_A_XY / POLYCC_SHIELD_K_V;
}

/* The backup near rest: hold the position (all three axes) where the vehicle got slow.  The z setpoint is
 * lowered by the PID's z integral offset (polycc_app_pid_zi_offset), as the app's own holds are: otherwise a
 * wound-up integral climbs the vehicle by Zi / zKp (0.13 m towards a ceiling after a take-off; real-firmware
 * SITL, where the climb was braked as backups). */
static void overrideHold(setpoint_t *sp, const float hold[3])
{
    sp->mode.x = modeAbs;
    sp->mode.y = modeAbs;
    sp->mode.z = modeAbs;
    sp->position.x = hold[0];
    sp->position.y = hold[1];
    sp->position.z = hold[2] - polycc_app_pid_zi_offset();
    sp->velocity.x = 0.0f;
    sp->velocity.y = 0.0f;
    sp->velocity.z = 0.0f;
    sp->velocity_body = false;
    sp->acceleration.x = 0.0f;
    sp->acceleration.y = 0.0f;
    sp->acceleration.z = 0.0f;
    trace.overrides += 1u;
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

/* A landing: the horizontal position held at at[], the source's vertical setpoint as sent while the
 * desired vertical velocity uz is not faster down than POLYCC_SHIELD_LAND_SPEED, that speed otherwise. */
static void overrideLand(setpoint_t *sp, const float at[2], float uz)
{
    sp->mode.x = modeAbs;
    sp->mode.y = modeAbs;
    sp->position.x = at[0];
    sp->position.y = at[1];
    sp->velocity.x = 0.0f;
    sp->velocity.y = 0.0f;
    sp->velocity_body = false;
    sp->acceleration.x = 0.0f;
    sp->acceleration.y = 0.0f;
    if (uz < -POLYCC_SHIELD_LAND_SPEED) {
        sp->mode.z = modeVelocity;
        sp->velocity.z = -POLYCC_SHIELD_LAND_SPEED;
        sp->acceleration.z = 0.0f;
    }
    trace.overrides += 1u;
}

/* The source asks for a descent straight down (POLYCC_SHIELD_LAND_*): its setpoint moves straight down (its
 * own velocity: a high-level land starts from the last setpoint, which may lie away from a vehicle the
 * shield held; the landing is flown where the vehicle is), or the PID aims straight down (a position
 * setpoint below the vehicle).  m the mailbox, landing: the previous decision was a landing (then any
 * descent goes on to touchdown: a position setpoint at the floor asks for less and less as the vehicle
 * nears it). */
static bool landingAsked(const mailbox_t *m, bool landing)
{
    const float h2 = POLYCC_SHIELD_HOLD_SPEED * POLYCC_SHIELD_HOLD_SPEED;
    const bool svDown = m->sv[2] < -POLYCC_SHIELD_HOLD_SPEED && m->sv[0] * m->sv[0] + m->sv[1] * m->sv[1] <= h2;
    const bool udDown = m->ud[2] < -POLYCC_SHIELD_HOLD_SPEED && m->ud[0] * m->ud[0] + m->ud[1] * m->ud[1] <= h2;
    const bool goOn = landing && (m->ud[2] < 0.0f || m->sv[2] < 0.0f) && m->sv[0] * m->sv[0] + m->sv[1] * m->sv[1] <= h2;
    return (svDown || udDown || goOn) &&
           m->vel[0] * m->vel[0] + m->vel[1] * m->vel[1] <= h2 &&
           m->vel[2] >= -(POLYCC_SHIELD_LAND_SPEED + POLYCC_SHIELD_HOLD_SPEED);
}

/* The desired velocity u leads away from the nearest obstacle: within 60 deg of psi's gradient g. */
static bool awayFrom(const float u[3], const float g[3])
{
    const float dot = (u[0] * g[0] + u[1] * g[1]) + u[2] * g[2];
    const float uu = (u[0] * u[0] + u[1] * u[1]) + u[2] * u[2];
    const float gg = (g[0] * g[0] + g[1] * g[1]) + g[2] * g[2];
    return dot > 0.0f && dot * dot >= 0.25f * (uu * gg);
}

/* The velocity flown under decision d (certified, not a brake or a landing) while the live setpoint asks for ud.
 * A pass decision follows the live request, held within POLYCC_SHIELD_PASS_TOL of the velocity it certified (per
 * component): continuous in ud.  Until 2026-12-06 it flew the live setpoint while that stayed within the tolerance
 * and jumped back to the 10-20 ms older certified velocity when it left it, so a source whose command changes by
 * about the tolerance per period was flown back and forth between its live and its old command (jerk that neither
 * the source nor the certificate asked for).  The band is the one a passed setpoint always had.  A filtered
 * decision flies exactly its certified command u: no band where the candidate deflects the source. */
static void flownVelocity(const decision_t *d, const float ud[3], float w[3])
{
    int i;
    for (i = 0; i < 3; ++i) {
        w[i] = d->pass ? clampf(ud[i], d->u[i] - POLYCC_SHIELD_PASS_TOL, d->u[i] + POLYCC_SHIELD_PASS_TOL) : d->u[i];
    }
}

static bool near3(const float a[3], const float b[3], float tol)
{
    return fabsf(a[0] - b[0]) <= tol && fabsf(a[1] - b[1]) <= tol && fabsf(a[2] - b[2]) <= tol;
}

/* ------------------------------------------------------------------ stabilizer side */
void polycc_controller_filter(setpoint_t *sp, const float pos[3], const float vel[3], const float acc[3],
                              float yaw_deg, uint32_t tick)
{
    float ud[3] = {0.0f, 0.0f, 0.0f}, sv[3], ub[3];
    bool manual = !desiredVelocity(sp, pos, yaw_deg, polycc_app_pid_zi(), ud, sv), isOn;
    const float gx = sp->mode.x == modeAbs ? sp->position.x - pos[0] : 0.0f;
    const float gy = sp->mode.y == modeAbs ? sp->position.y - pos[1] : 0.0f;
    decision_t d;
    bool bridge;
    taskENTER_CRITICAL();
    memcpy(mbox.pos, pos, sizeof mbox.pos);
    memcpy(mbox.vel, vel, sizeof mbox.vel);
    memcpy(mbox.acc, acc, sizeof mbox.acc);
    memcpy(mbox.ud, ud, sizeof mbox.ud);
    memcpy(mbox.sv, sv, sizeof mbox.sv);
    mbox.gap2 = gx * gx + gy * gy;
    mbox.tick = tick;
    mbox.manual = manual;
    mbox.valid = true;
    if (next.valid && (int32_t)(tick - next.from) >= 0) { /* the pending decision becomes current */
        cur = next;
        next.valid = false;
    }
    d = cur;
    /* The current decision ran out while its successor is planned but not yet due: the app task planned
     * late (its mailbox tick, hence its `from`, is past this decision's `to`).  The successor's plan modelled
     * exactly this decision's command (its u_app) over its latency, n_lat = 3 periods from its estimate (20 ms
     * of estimator delay, then the 10 ms to its `from`), so flying this decision on until the successor is due
     * is what a certified plan modelled.  A successor that is a backup or a landing (the uncertified
     * exception) certifies nothing: brake as before.  Braking here instead was a 1-10 ms brake pulse whenever
     * the app woke a tick late, which the PID position loop turned into 10 ms of the brake's tilt (jerk
     * spikes of ~200 m/s^3 at 3 m/s in the real-firmware SITL on a busy host). */
    bridge = d.valid && (int32_t)(tick - d.to) >= 0 && next.valid && !next.brake && !next.land;
    isOn = on;
    taskEXIT_CRITICAL();
    if (!isOn) {
        holding = false;
        return;
    }
    if (manual) {
        if (!warnedManual) {
            DEBUG_PRINT("shield: manual attitude/rate setpoint passed unfiltered (not protected)\n");
            warnedManual = true;
        }
        trace.manual += 1u;
        trace.status = POLYCC_SHIELD_STATUS_MANUAL;
        return;
    }
    if (!d.valid) { /* just switched on: the first decision is on its way */
        return;
    }
    if (bridge) {
        trace.bridged += 1u;
    }
    if (d.land && !bridge && (int32_t)(tick - d.to) >= 0 && (ud[2] < 0.0f || sv[2] < 0.0f) &&
        vel[0] * vel[0] + vel[1] * vel[1] <= POLYCC_SHIELD_HOLD_SPEED * POLYCC_SHIELD_HOLD_SPEED) {
        /* A landing whose next decision is late (the app task did not run in time): the descent goes on
         * while the source still descends and the vehicle does not drift, as that decision would continue it
         * (landingAsked, landing = true). Braking instead stopped the descent, the vehicle lagged the
         * high-level land and its motor stop dropped it from 0.24 m (real-firmware SITL, a loaded CI host). */
        holding = false;
        overrideLand(sp, d.at, ud[2]);
        return;
    }
    if (((int32_t)(tick - d.to) >= 0 && !bridge) || d.brake) { /* the backup, or a decision not replaced in time */
        if (!d.brake) {
            trace.expired += 1u;
        }
        if (!holding && (vel[0] * vel[0] + vel[1] * vel[1]) + vel[2] * vel[2] <=
                            POLYCC_SHIELD_HOLD_SPEED * POLYCC_SHIELD_HOLD_SPEED) {
            memcpy(holdAt, pos, sizeof holdAt);
            holding = true;
        }
        if (holding) {
            overrideHold(sp, holdAt);
        } else {
            polycc_shield_brake(ub, vel, brakeErr());
            override(sp, ub);
        }
        return;
    }
    holding = false;
    if (d.land) {
        overrideLand(sp, d.at, ud[2]);
        return;
    }
    if (d.pass && near3(ud, d.planned, POLYCC_SHIELD_PASS_TOL)) {
        return; /* the setpoint as sent (its own mode: a position setpoint stays one) */
    }
    flownVelocity(&d, ud, ub);
    override(sp, ub);
}

/* ------------------------------------------------------------------ app side */
static void switchOff(uint8_t status)
{
    taskENTER_CRITICAL();
    on = false;
    cur.valid = false;
    next.valid = false;
    taskEXIT_CRITICAL();
    planned = false;
    trace.on = 0u;
    trace.status = status;
}

void polycc_controller_plan(uint32_t now)
{
    mailbox_t m;
    decision_t d;
    const float *uApp;
    float speed2, udxy2;
    float uB[3], uF[3];
    bool landNow;
    decision_t prev;
    uint32_t f;
    if (!pOn && !on) {
        trace.status = POLYCC_SHIELD_STATUS_OFF;
        return;
    }
    if (planned && (uint32_t)(now - lastPlan) < POLYCC_SHIELD_PERIOD_TICKS) {
        return;
    }
    if (polycc_controller_max_evals() == 0u) {
        if (!warnedSlow) {
            DEBUG_PRINT("shield refused: the scene's worst case (%u cycles) does not fit %u %% of a 10 ms period\n",
                        (unsigned)polycc_app_scene_worst_cycles(), (unsigned)POLYCC_SHIELD_CPU_SHARE_PERCENT);
            warnedSlow = true;
        }
        switchOff(POLYCC_SHIELD_STATUS_TOO_SLOW);
        return;
    }
    taskENTER_CRITICAL();
    m = mbox;
    d = cur;
    taskEXIT_CRITICAL();
    if (!m.valid || (uint32_t)(now - m.tick) > 2u * POLYCC_SHIELD_PERIOD_TICKS) {
        switchOff(POLYCC_SHIELD_STATUS_NO_CONTROLLER); /* the out-of-tree controller does not run */
        return;
    }
    speed2 = (m.vel[0] * m.vel[0] + m.vel[1] * m.vel[1]) + m.vel[2] * m.vel[2];
    udxy2 = m.ud[0] * m.ud[0] + m.ud[1] * m.ud[1];
    if (!pOn) {
        /* Safe hand-over: when the source's setpoint is manual, or lies (horizontally) where the vehicle
         * is and either the shield passes it unchanged or the vehicle is at rest and the source asks it
         * to stay or to go straight down (a hover at the brake edge is never certified; landing ends
         * every flight).  Not merely "at rest" or "passed": a vehicle held in front of a box by a
         * high-level go_to whose setpoint lies behind it is at rest, and its setpoint's velocity can
         * point away from the box for a moment; releasing it then flew it into the box on the real
         * firmware (the PID chases the setpoint's position). */
        const bool here = m.gap2 <= POLYCC_SHIELD_HANDBACK_GAP * POLYCC_SHIELD_HANDBACK_GAP;
        const bool rest = speed2 <= POLYCC_SHIELD_HOLD_SPEED * POLYCC_SHIELD_HOLD_SPEED &&
                          udxy2 <= POLYCC_SHIELD_HOLD_SPEED * POLYCC_SHIELD_HOLD_SPEED &&
                          m.ud[2] <= POLYCC_SHIELD_HOLD_SPEED;
        if (!d.valid || m.manual || (here && (d.pass || rest))) {
            switchOff(POLYCC_SHIELD_STATUS_OFF);
            return;
        }
        trace.status = POLYCC_SHIELD_STATUS_OFF_PENDING;
    } else if (!on) {
        on = true;
        warnedManual = false;
        trace.status = POLYCC_SHIELD_STATUS_STARTING;
    }
    trace.on = 1u;
    lastPlan = now;
    planned = true;
    if (m.manual) {
        return;
    }
    fillParams(&jobPrm);
    /* At the tube's edge: a vehicle held where psi = tube can certify nothing (the first sample covers a
     * ball of radius psi - tube = 0), not even leaving, and was held there until the source stopped the
     * motors (regression: a go_to back from a box on the real firmware, then a drop from 0.54 m).  When the
     * source asks to move away from the nearest obstacle, the plan keeps psi >= (its last value -
     * POLYCC_SHIELD_ESCAPE_DEPTH) instead, never below 0 (clearance r). */
    if (d.valid && lPsi < jobPrm.tube + POLYCC_SHIELD_ESCAPE_DEPTH && awayFrom(m.ud, job.grad)) {
        const float t = lPsi - POLYCC_SHIELD_ESCAPE_DEPTH;
        jobPrm.tube = t > 0.0f ? t : 0.0f;
        trace.escapes += 1u;
    }
    if (d.valid && d.brake) { /* flown as the brake policy: its command at this estimate */
        polycc_shield_brake(uB, m.vel, brakeErr());
        uApp = uB;
    } else if (d.valid && !d.land) { /* what the stabilizer flies under the current decision at this setpoint */
        flownVelocity(&d, m.ud, uF);
        uApp = uF;
    } else {
        uApp = d.valid ? d.u : m.ud;
    }
    f = polycc_shield_run(&job, polycc_app_scene(), &jobPrm, m.pos, m.vel, m.acc, uApp, m.ud);
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
    prev = d;
    memset(&d, 0, sizeof d);
    d.valid = true;
    d.from = m.tick + POLYCC_SHIELD_PERIOD_TICKS;
    d.to = m.tick + (1u + POLYCC_SHIELD_N_COMMIT) * POLYCC_SHIELD_PERIOD_TICKS; /* certified to there */
    memcpy(d.planned, m.ud, sizeof d.planned);
    /* A landing starts when the shield would not pass the setpoint unchanged, and once started goes on while the
     * setpoint descends, passable or not: passing would chase the setpoint's x, y (a high-level land starts
     * from the last setpoint, away from a held vehicle), and a brake in between stops the descent, so the
     * vehicle lagged the land and the planner's motor stop dropped it (6 cm, a loaded CI machine). */
    landNow = landingAsked(&m, prev.valid && prev.land) &&
              ((prev.valid && prev.land) ||
               !((f & POLYCC_SHIELD_CERTIFIED) && !(f & (POLYCC_SHIELD_ACTIVE | POLYCC_SHIELD_SATURATED))));
    if (landNow) { /* touch down on what is below instead of hovering over it (POLYCC_SHIELD_LAND_*) */
        d.land = true;
        if (prev.valid && prev.land) {
            memcpy(d.at, prev.at, sizeof d.at);
        } else {
            d.at[0] = m.pos[0];
            d.at[1] = m.pos[1];
        }
        d.u[2] = m.ud[2] > -POLYCC_SHIELD_LAND_SPEED ? m.ud[2] : -POLYCC_SHIELD_LAND_SPEED;
        trace.landings += 1u;
        if (pOn) {
            trace.status = POLYCC_SHIELD_STATUS_LANDING;
        }
    } else if (f & POLYCC_SHIELD_CERTIFIED) {
        trace.certified += 1u;
        memcpy(d.u, job.u_c, sizeof d.u);
        d.pass = !(f & (POLYCC_SHIELD_ACTIVE | POLYCC_SHIELD_SATURATED));
        if (pOn) {
            trace.status = d.pass ? POLYCC_SHIELD_STATUS_PASS : POLYCC_SHIELD_STATUS_FILTERED;
        }
    } else {
        trace.backups += 1u;
        d.brake = true;
        polycc_shield_brake(d.u, m.vel, brakeErr());
        if (pOn) {
            trace.status = POLYCC_SHIELD_STATUS_BACKUP;
        }
    }
    memcpy(trace.u, d.u, sizeof d.u);
    taskENTER_CRITICAL();
    next = d;
    taskEXIT_CRITICAL();
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
    /* The FreeRTOS tick, not stabilizerStep: the app side stamps its decisions with xTaskGetTickCount(),
     * and stabilizerStep starts at 1 only after calibration, seconds behind it (on the real firmware a
     * stabilizerStep stamp made every mailbox look stale: status 8, the shield off while enabled). */
    polycc_controller_filter(&sp, pos, vel, acc, state->attitude.yaw, (uint32_t)xTaskGetTickCount());
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
/** @brief Agent radius r the shield keeps clear, m (default 0.1) */
PARAM_ADD(PARAM_FLOAT, radius, &pRadius)
/** @brief Model-tracking allowance e_tube, m (default 0.05) */
PARAM_ADD(PARAM_FLOAT, tube, &pTube)
/** @brief Speed cap of the filtered command, m/s (default 3) */
PARAM_ADD(PARAM_FLOAT, vmax, &pVmax)
/** @brief ECBF gain on the barrier rate, 1/s (default 4) */
PARAM_ADD(PARAM_FLOAT, k1, &pK1)
/** @brief ECBF gain on the barrier, 1/s^2 (default 4) */
PARAM_ADD(PARAM_FLOAT, k0, &pK0)
/** @brief Clearance cap D on psi, m (0: off; psi <- min(psi, D), flat beyond D, as a capped spatial index) */
PARAM_ADD(PARAM_FLOAT, psicap, &pPsiCap)
PARAM_GROUP_STOP(polyccShield)

/**
 * polycc shield state.
 */
LOG_GROUP_START(polyccShield)
/** @brief 0 off, 1 pass, 2 filtered, 3 backup (braking), 4 manual (unfiltered), 5 off pending, 6 too slow, 7 starting,
 * 8 no out-of-tree controller, 9 landing */
LOG_ADD(LOG_UINT8, status, &trace.status)
/** @brief Decisions made (100 Hz while on) */
LOG_ADD(LOG_UINT32, decisions, &trace.decisions)
/** @brief Decisions that flew the backup (brake to hover) */
LOG_ADD(LOG_UINT32, backups, &trace.backups)
/** @brief ECBF candidates infeasible within vmax */
LOG_ADD(LOG_UINT32, infeasible, &trace.infeasible)
/** @brief Ticks with a manual setpoint passed unfiltered */
LOG_ADD(LOG_UINT32, manual, &trace.manual)
/** @brief Decisions flown as a landing (a descent asked straight down) */
LOG_ADD(LOG_UINT32, landings, &trace.landings)
/** @brief Plans made with the tube lowered to leave its edge (moving away from the nearest obstacle) */
LOG_ADD(LOG_UINT32, escapes, &trace.escapes)
/** @brief Ticks a decision was flown on past its end until its late, certified successor was due */
LOG_ADD(LOG_UINT32, bridged, &trace.bridged)
/** @brief Ticks braked because a decision ran out with no certified successor planned (the app task late) */
LOG_ADD(LOG_UINT32, expired, &trace.expired)
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
