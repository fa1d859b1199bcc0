/* Host model of the firmware's commander, high-level commander and the supervisor's setpoint
 * handling, following crazyflie-firmware's commander.c, crtp_commander_high_level.c, planner.c,
 * supervisor.c and stabilizer.c (behaviour re-implemented from their documented interface; no
 * firmware code is copied).  The real-firmware SITL (polycc/sim/firmware/) is the reference; a
 * differential test flies the same scenarios in both.
 *
 *   commander:  a setpoint replaces the current one when its priority is at least the current
 *               one's; one above HIGHLEVEL stops the high-level planner; commanderRelaxPriority
 *               drops the priority to LOWEST and tells the planner the current state.
 *   high-level: IDLE / FLYING / LANDING; takeoff (only from IDLE), go_to, land plan a 7th-order
 *               polynomial from the current position, velocity and acceleration to rest at the
 *               target; a finished landing returns to IDLE.  Evaluated at 100 Hz (RATE_HL_COMMANDER)
 *               and fed to the commander at priority HIGHLEVEL; while IDLE ("stopped") it gives the
 *               null setpoint (motors off) -- which the commander only uses when nothing of higher
 *               priority is active.
 *   supervisor: a setpoint older than 500 ms levels the vehicle (x, y disabled, attitude 0, z kept),
 *               older than 2 s is replaced by the null setpoint; "flying" means the motors ran
 *               within the last 2 s.
 */
#include <math.h>
#include <string.h>

#include "commander.h"
#include "config.h"
#include "controller.h"
#include "controller_pid.h"
#include "crtp.h"
#include "crtp_commander_high_level.h"
#include "polycc_shim.h"
#include "sim_internal.h"
#include "supervisor.h"

#define HL_PERIOD_TICKS 10u /* RATE_HL_COMMANDER = 100 Hz */
#define WDT_STABILIZE_TICKS 500u
#define WDT_SHUTDOWN_TICKS 2000u
#define FLYING_HYSTERESIS_TICKS 2000u
/* The firmware's stabilizerStep is not the tick count: stabilizerTask sets it to 1 once the sensors are
 * calibrated (src/modules/src/stabilizer.c) and counts loops from there, so it lags xTaskGetTickCount() by
 * the boot and calibration time (~1-3 s). The shim models a 1.5 s lag, so app code that mixes the two
 * clocks fails here as it does on the real firmware (the shield did, and reported status 8). */
#define STABILIZER_START_TICK 1500u

static shim_commander_record_t rec;
static setpoint_t current;      /* the commander's setpoint queue */
static const setpoint_t nullSetpoint;
static setpoint_t effective;    /* what the controller got at the last stabilizer step */
static setpoint_t pidSetpoint; /* what controllerPid() got (out-of-tree controller) */
static uint32_t pidCalls;
static float accG[3]; /* state.acc, Gs */
static int motorsOn;
static uint32_t lastMotorsTick;
static int everFlew;
static ControllerType controllerType = ControllerTypePID;
static int connected = 1;
static int locked, crashed, tumbled;
static state_t lastState;
static uint32_t lastHlTick;

/* ---------------------------------------------------------------- high-level planner */
typedef enum { HL_IDLE = 0, HL_FLYING, HL_LANDING } hl_state_t;
static hl_state_t hlState;
static double hlT0, hlDur;
static double hlC[4][8]; /* x, y, z, yaw: coefficients in s = (t - t0) / T */
static double hlPos[3], hlVel[3], hlYaw; /* initial conditions when stopped (the state, deg -> rad) */
static int hlCalls[4];                   /* takeoff, land, go_to, stop */
/* A land queued by the test for the high-level commander's task (shim_hl_queue_land). */
static int hlPending, hlPendingArmed;
static float hlPendingHeight, hlPendingDuration;

static double nowS(void)
{
    return (double)shim_get_tick() * 1e-3;
}

/* p(s) = sum c_k s^k on [0, 1]: p, T p', T^2 p'', T^3 p''' given at 0 (jerk 0), rest at p1 at 1. */
static void septic(double p0, double v0, double a0, double p1, double T, double c[8])
{
    /* unknowns c4..c7 from the four end conditions; the inverse of
     * [[1,1,1,1],[4,5,6,7],[12,20,30,42],[24,60,120,210]] */
    static const double inv[4][4] = {
        {35.0, -15.0, 2.5, -1.0 / 6.0},
        {-84.0, 39.0, -7.0, 0.5},
        {70.0, -34.0, 6.5, -0.5},
        {-20.0, 10.0, -2.0, 1.0 / 6.0},
    };
    double b[4];
    int i, j;
    c[0] = p0;
    c[1] = v0 * T;
    c[2] = 0.5 * a0 * T * T;
    c[3] = 0.0;
    b[0] = p1 - (c[0] + c[1] + c[2] + c[3]);
    b[1] = -(c[1] + 2.0 * c[2] + 3.0 * c[3]);
    b[2] = -(2.0 * c[2] + 6.0 * c[3]);
    b[3] = -(6.0 * c[3]);
    for (i = 0; i < 4; ++i) {
        c[4 + i] = 0.0;
        for (j = 0; j < 4; ++j) {
            c[4 + i] += inv[i][j] * b[j];
        }
    }
}

/* Position, velocity, acceleration of coordinate k at time t. */
static void hlEval(int k, double t, double *p, double *v, double *a)
{
    double s = hlDur > 0.0 ? (t - hlT0) / hlDur : 1.0, P = 0.0, V = 0.0, A = 0.0, sk = 1.0;
    int i;
    if (s > 1.0) {
        s = 1.0;
    }
    if (s < 0.0) {
        s = 0.0;
    }
    for (i = 0; i < 8; ++i) {
        P += hlC[k][i] * sk;
        if (i + 1 < 8) {
            V += (double)(i + 1) * hlC[k][i + 1] * sk;
        }
        if (i + 2 < 8) {
            A += (double)((i + 2) * (i + 1)) * hlC[k][i + 2] * sk;
        }
        sk *= s;
    }
    *p = P;
    *v = s < 1.0 ? V / hlDur : 0.0;
    *a = s < 1.0 ? A / (hlDur * hlDur) : 0.0;
}

static void hlStart(const double target[3], double yaw, double duration, hl_state_t state)
{
    double p0[4], v0[4], a0[4];
    double t = nowS();
    int k;
    if (hlState == HL_IDLE) {
        for (k = 0; k < 3; ++k) {
            p0[k] = hlPos[k];
            v0[k] = hlVel[k];
            a0[k] = 0.0;
        }
        p0[3] = hlYaw;
        v0[3] = a0[3] = 0.0;
    } else {
        for (k = 0; k < 4; ++k) {
            hlEval(k, t, &p0[k], &v0[k], &a0[k]);
        }
    }
    hlT0 = t;
    hlDur = duration > 1e-3 ? duration : 1e-3;
    for (k = 0; k < 3; ++k) {
        septic(p0[k], v0[k], a0[k], target[k], hlDur, hlC[k]);
    }
    septic(p0[3], v0[3], a0[3], yaw, hlDur, hlC[3]);
    hlState = state;
}

static int hlFinished(void)
{
    return nowS() >= hlT0 + hlDur;
}

bool crtpCommanderHighLevelIsStopped(void)
{
    shimHlTaskRun();
    hlPendingArmed = hlPending; /* its packet arrives right after this check */
    return hlState == HL_IDLE;
}

bool crtpCommanderHighLevelIsTrajectoryFinished(void)
{
    return hlState != HL_IDLE && hlFinished();
}

int crtpCommanderHighLevelTakeoffYaw(const float absoluteHeight_m, const float duration_s, const float yaw)
{
    double target[3];
    ++hlCalls[0];
    if (hlState != HL_IDLE) {
        return 1;
    }
    target[0] = hlPos[0];
    target[1] = hlPos[1];
    target[2] = (double)absoluteHeight_m;
    hlStart(target, (double)yaw, (double)duration_s, HL_FLYING);
    return 0;
}

int crtpCommanderHighLevelTakeoff(const float absoluteHeight_m, const float duration_s)
{
    return crtpCommanderHighLevelTakeoffYaw(absoluteHeight_m, duration_s, (float)hlYaw);
}

int crtpCommanderHighLevelLandYaw(const float absoluteHeight_m, const float duration_s, const float yaw)
{
    double target[3], p, v, a;
    int k;
    ++hlCalls[1];
    if (hlState == HL_LANDING) {
        return 1;
    }
    for (k = 0; k < 2; ++k) {
        if (hlState == HL_IDLE) {
            target[k] = hlPos[k];
        } else {
            hlEval(k, nowS(), &p, &v, &a);
            target[k] = p;
        }
    }
    target[2] = (double)absoluteHeight_m;
    hlStart(target, (double)yaw, (double)duration_s, HL_LANDING);
    return 0;
}

int crtpCommanderHighLevelLand(const float absoluteHeight_m, const float duration_s)
{
    double p, v, a;
    float yaw = (float)hlYaw;
    if (hlState != HL_IDLE) {
        hlEval(3, nowS(), &p, &v, &a);
        yaw = (float)p;
    }
    return crtpCommanderHighLevelLandYaw(absoluteHeight_m, duration_s, yaw);
}

int crtpCommanderHighLevelStop(void)
{
    ++hlCalls[3];
    hlState = HL_IDLE;
    return 0;
}

int crtpCommanderHighLevelGoTo(const float x, const float y, const float z, const float yaw, const float duration_s,
                               const bool relative)
{
    double target[3];
    shimHlTaskRun();
    ++hlCalls[2];
    target[0] = (double)x;
    target[1] = (double)y;
    target[2] = (double)z;
    if (relative) {
        double p, v, a;
        int k;
        for (k = 0; k < 3; ++k) {
            if (hlState == HL_IDLE) {
                p = hlPos[k];
            } else {
                hlEval(k, nowS(), &p, &v, &a);
            }
            target[k] += p;
        }
    }
    hlStart(target, (double)yaw, (double)duration_s, HL_FLYING);
    return 0;
}

void crtpCommanderHighLevelTellState(const state_t *state)
{
    hlPos[0] = (double)state->position.x;
    hlPos[1] = (double)state->position.y;
    hlPos[2] = (double)state->position.z;
    hlVel[0] = (double)state->velocity.x;
    hlVel[1] = (double)state->velocity.y;
    hlVel[2] = (double)state->velocity.z;
    hlYaw = (double)state->attitude.yaw * (3.14159265358979 / 180.0);
}

/* crtpCommanderHighLevelGetSetpoint: 1 if it produced a setpoint. */
static int hlGetSetpoint(setpoint_t *sp, const state_t *state)
{
    double p, v, a;
    int k;
    if (hlState == HL_IDLE) {
        crtpCommanderHighLevelTellState(state);
        *sp = nullSetpoint;
        return 1;
    }
    if (hlState == HL_LANDING && hlFinished()) {
        hlState = HL_IDLE;
        crtpCommanderHighLevelTellState(state);
        *sp = nullSetpoint;
        return 1;
    }
    memset(sp, 0, sizeof *sp);
    for (k = 0; k < 3; ++k) {
        hlEval(k, nowS(), &p, &v, &a);
        (&sp->position.x)[k] = (float)p;
        (&sp->velocity.x)[k] = (float)v;
        (&sp->acceleration.x)[k] = (float)a;
    }
    hlEval(3, nowS(), &p, &v, &a);
    sp->attitude.yaw = (float)(p * (180.0 / 3.14159265358979));
    sp->attitudeRate.yaw = (float)(v * (180.0 / 3.14159265358979));
    sp->mode.x = modeAbs;
    sp->mode.y = modeAbs;
    sp->mode.z = modeAbs;
    sp->mode.yaw = modeAbs;
    return 1;
}

/* A firmware ASSERT (assertFail): motors stopped for good (the Crazyflie resets). */
static int asserted;

void shimAssertFailed(void)
{
    asserted = 1;
}

/* ---------------------------------------------------------------- commander */
void shimCommanderReset(void)
{
    asserted = 0;
    memset(&rec, 0, sizeof rec);
    pidSetpoint = nullSetpoint;
    pidCalls = 0u;
    accG[0] = accG[1] = accG[2] = 0.0f;
    current = nullSetpoint;
    effective = nullSetpoint;
    rec.active_priority = COMMANDER_PRIORITY_DISABLE;
    motorsOn = 0;
    lastMotorsTick = 0;
    everFlew = 0;
    hlState = HL_IDLE;
    memset(hlPos, 0, sizeof hlPos);
    memset(hlVel, 0, sizeof hlVel);
    hlYaw = 0.0;
    memset(hlCalls, 0, sizeof hlCalls);
    hlPending = hlPendingArmed = 0;
    memset(&lastState, 0, sizeof lastState);
    lastHlTick = 0u;
    controllerType = ControllerTypePID;
    connected = 1;
    locked = crashed = tumbled = 0;
}

void commanderInit(void)
{
    shimCommanderReset();
}

bool commanderTest(void)
{
    return true;
}

static void record(const setpoint_t *sp, int priority)
{
    ++rec.count;
    rec.tick = sp->timestamp;
    rec.priority = priority;
    rec.mode_x = (int)sp->mode.x;
    rec.mode_y = (int)sp->mode.y;
    rec.mode_z = (int)sp->mode.z;
    rec.mode_roll = (int)sp->mode.roll;
    rec.mode_pitch = (int)sp->mode.pitch;
    rec.mode_yaw = (int)sp->mode.yaw;
    rec.velocity_body = sp->velocity_body ? 1 : 0;
    rec.vx = sp->velocity.x;
    rec.vy = sp->velocity.y;
    rec.vz = sp->velocity.z;
    rec.px = sp->position.x;
    rec.py = sp->position.y;
    rec.pz = sp->position.z;
    rec.yaw_rate = sp->attitudeRate.yaw;
}

void commanderSetSetpoint(setpoint_t *setpoint, int priority)
{
    shimHlTaskRun();
    if (priority < rec.active_priority) {
        ++rec.rejected;
        return;
    }
    setpoint->timestamp = shim_get_tick();
    current = *setpoint;
    rec.active_priority = priority;
    if (priority > COMMANDER_PRIORITY_HIGHLEVEL) {
        crtpCommanderHighLevelStop();
        record(setpoint, priority);
    }
}

int commanderGetActivePriority(void)
{
    return rec.active_priority;
}

void commanderRelaxPriority(void)
{
    shimHlTaskRun();
    ++rec.relax_count;
    crtpCommanderHighLevelTellState(&lastState);
    rec.active_priority = COMMANDER_PRIORITY_LOWEST;
}

uint32_t commanderGetInactivityTime(void)
{
    return shim_get_tick() - current.timestamp;
}

void commanderGetSetpoint(setpoint_t *setpoint, const state_t *state)
{
    *setpoint = current;
    lastState = *state;
}

void shim_commander_get(shim_commander_record_t *out)
{
    *out = rec;
    out->hl_state = (int)hlState;
    out->hl_takeoffs = hlCalls[0];
    out->hl_lands = hlCalls[1];
    out->hl_gotos = hlCalls[2];
    out->hl_stops = hlCalls[3];
}

/* ---------------------------------------------------------------- stabilizer step */
/* Motors off: the PID controller passes setpoint.thrust through when z is not controlled, and zero
 * thrust turns the motors off (controller_pid.c; power distribution, idleThrust 0). That covers
 * the null setpoint and a manual (rpyt) setpoint with thrust 0, e.g. the one cflib's close_link()
 * sends. */
static int isNull(const setpoint_t *sp)
{
    return sp->mode.z == modeDisable && !(sp->thrust > 0.0f);
}

/* The PID controller as the out-of-tree controller calls it: the host records what it gets. */

void controllerPidInit(void) {}

bool controllerPidTest(void)
{
    return true;
}

void controllerPid(control_t *control, const setpoint_t *setpoint, const sensorData_t *sensors, const state_t *state,
                   const stabilizerStep_t stabilizerStep)
{
    (void)control;
    (void)sensors;
    (void)state;
    (void)stabilizerStep;
    pidSetpoint = *setpoint;
    ++pidCalls;
}

void shim_set_acceleration(float ax, float ay, float az)
{
    accG[0] = ax / 9.81f;
    accG[1] = ay / 9.81f;
    accG[2] = az / 9.81f;
}

uint32_t shim_pid_calls(void)
{
    return pidCalls;
}

void shim_stabilizer_step(const float pos[3], const float vel[3], float yaw_deg, shim_setpoint_t *out)
{
    state_t state;
    setpoint_t sp, hl;
    uint32_t tick = shim_get_tick(), age;
    memset(&state, 0, sizeof state);
    state.position.x = pos[0];
    state.position.y = pos[1];
    state.position.z = pos[2];
    state.velocity.x = vel[0];
    state.velocity.y = vel[1];
    state.velocity.z = vel[2];
    state.attitude.yaw = yaw_deg;
    state.acc.x = accG[0];
    state.acc.y = accG[1];
    state.acc.z = accG[2];
    if (!locked && (tick - lastHlTick >= HL_PERIOD_TICKS || tick < lastHlTick) && hlGetSetpoint(&hl, &state)) {
        lastHlTick = tick;
        commanderSetSetpoint(&hl, COMMANDER_PRIORITY_HIGHLEVEL);
    }
    commanderGetSetpoint(&sp, &state);
    age = tick - sp.timestamp;
    if (asserted || locked || crashed || tumbled || age > WDT_SHUTDOWN_TICKS) {
        sp = nullSetpoint;
    } else if (age > WDT_STABILIZE_TICKS) {
        sp.mode.x = modeDisable;
        sp.mode.y = modeDisable;
        sp.mode.roll = modeAbs;
        sp.mode.pitch = modeAbs;
        sp.mode.yaw = modeVelocity;
        sp.attitude.roll = 0.0f;
        sp.attitude.pitch = 0.0f;
        sp.attitudeRate.yaw = 0.0f;
    }
    motorsOn = !isNull(&sp);
    if (controllerType == ControllerTypeOot) { /* the stabilizer's controller() call: shield, then PID */
        controllerOutOfTree(0, &sp, 0, &state, (stabilizerStep_t)(tick + 1u - STABILIZER_START_TICK));
        sp = pidSetpoint;
    }
    effective = sp;
    if (motorsOn) {
        lastMotorsTick = tick;
        everFlew = 1;
    }
    out->motors_on = motorsOn;
    out->mode_x = (int)sp.mode.x;
    out->mode_y = (int)sp.mode.y;
    out->mode_z = (int)sp.mode.z;
    out->mode_roll = (int)sp.mode.roll;
    out->mode_pitch = (int)sp.mode.pitch;
    out->mode_yaw = (int)sp.mode.yaw;
    out->velocity_body = sp.velocity_body ? 1 : 0;
    out->px = sp.position.x;
    out->py = sp.position.y;
    out->pz = sp.position.z;
    out->vx = sp.velocity.x;
    out->vy = sp.velocity.y;
    out->vz = sp.velocity.z;
    out->ax = sp.acceleration.x;
    out->ay = sp.acceleration.y;
    out->az = sp.acceleration.z;
    out->roll = sp.attitude.roll;
    out->pitch = sp.attitude.pitch;
    out->yaw = sp.attitude.yaw;
    out->yaw_rate = sp.attitudeRate.yaw;
    out->thrust = sp.thrust;
    out->priority = rec.active_priority;
    out->age_ms = age;
}

/* ---------------------------------------------------------------- supervisor, controller, link */
bool supervisorIsFlying(void)
{
    return everFlew && (shim_get_tick() - lastMotorsTick) < FLYING_HYSTERESIS_TICKS;
}

bool supervisorIsTumbled(void)
{
    return tumbled != 0;
}

bool supervisorIsArmed(void)
{
    return true;
}

bool supervisorIsLocked(void)
{
    return locked != 0;
}

bool supervisorIsCrashed(void)
{
    return crashed != 0;
}

bool supervisorCanFly(void)
{
    return !locked && !crashed && !tumbled;
}

void shim_set_supervisor(int is_locked, int is_crashed, int is_tumbled)
{
    locked = is_locked;
    crashed = is_crashed;
    tumbled = is_tumbled;
}

int shim_motors_on(void)
{
    return motorsOn;
}

ControllerType controllerGetType(void)
{
    return controllerType;
}

const char *controllerGetName(void)
{
    static const char *names[] = {"Any", "PID", "Mellinger", "INDI", "Brescianini", "Lee"};
    return (unsigned)controllerType < ControllerType_COUNT ? names[controllerType] : "?";
}

void shim_set_controller(int type)
{
    controllerType = (ControllerType)type;
}

bool crtpIsConnected(void)
{
    return connected != 0;
}

void shim_set_connected(int is_connected)
{
    connected = is_connected;
}

/* A client's setpoint (cflib's commander packets, or the SITL's initial hover), given in the
 * shim_setpoint_t layout; motors_on = 0 sends the null (stop) setpoint. */
void shim_commander_set(const shim_setpoint_t *in, int priority)
{
    setpoint_t sp;
    memset(&sp, 0, sizeof sp);
    if (in->motors_on) {
        sp.mode.x = (stab_mode_t)in->mode_x;
        sp.mode.y = (stab_mode_t)in->mode_y;
        sp.mode.z = (stab_mode_t)in->mode_z;
        sp.mode.roll = (stab_mode_t)in->mode_roll;
        sp.mode.pitch = (stab_mode_t)in->mode_pitch;
        sp.mode.yaw = (stab_mode_t)in->mode_yaw;
        sp.velocity_body = in->velocity_body != 0;
        sp.position.x = in->px;
        sp.position.y = in->py;
        sp.position.z = in->pz;
        sp.velocity.x = in->vx;
        sp.velocity.y = in->vy;
        sp.velocity.z = in->vz;
        sp.acceleration.x = in->ax;
        sp.acceleration.y = in->ay;
        sp.acceleration.z = in->az;
        sp.attitude.roll = in->roll;
        sp.attitude.pitch = in->pitch;
        sp.attitude.yaw = in->yaw;
        sp.attitudeRate.yaw = in->yaw_rate;
        sp.thrust = in->thrust;
    }
    commanderSetSetpoint(&sp, priority);
}

/* cflib's notify_setpoint_stop: the firmware relaxes the priority (remain_ms is an artifact of an
 * older design and ignored, crtp_commander.c notifySetpointsStopDecoder). */
void shim_commander_notify_stop(int remain_ms)
{
    (void)remain_ms;
    commanderRelaxPriority();
}

/* The state after a finished high-level takeoff: hovering at (x, y, z) under the high-level
 * commander (planner flying, trajectory done), no setpoint of higher priority. */
void shim_hl_hover_at(float x, float y, float z)
{
    double target[3];
    hlPos[0] = (double)x;
    hlPos[1] = (double)y;
    hlPos[2] = (double)z;
    memset(hlVel, 0, sizeof hlVel);
    hlState = HL_IDLE;
    target[0] = hlPos[0];
    target[1] = hlPos[1];
    target[2] = hlPos[2];
    hlStart(target, hlYaw, 1e-3, HL_FLYING);
    hlT0 = nowS() - 1.0;
    rec.active_priority = COMMANDER_PRIORITY_LOWEST;
    everFlew = 1;
    lastMotorsTick = shim_get_tick();
}

/* ---------------------------------------------------------------- the high-level commander's task */
void shim_hl_queue_land(float height, float duration)
{
    hlPending = 1;
    hlPendingArmed = 0;
    hlPendingHeight = height;
    hlPendingDuration = duration;
}

static int hlCarryOut(void)
{
    hlPending = hlPendingArmed = 0;
    (void)crtpCommanderHighLevelLand(hlPendingHeight, hlPendingDuration);
    return 1;
}

void shimHlTaskRun(void)
{
    if (hlPending && hlPendingArmed && shimTaskPriority() < CMD_HIGH_LEVEL_TASK_PRI) {
        (void)hlCarryOut();
    }
}

int shim_hl_run_pending(void)
{
    return hlPending ? hlCarryOut() : 0;
}
