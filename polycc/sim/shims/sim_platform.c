/* Host versions of the firmware log and parameter groups that standard Crazyflie tools use
 * (cflib's MotionCommander and PositionHlCommander, cfclient's tabs) and that the app reads:
 * stabilizer.{roll,pitch,yaw,thrust} and stabilizer.controller/estimator, commander.enHighLevel,
 * kalman.resetEstimation, supervisor.info, pm.vbat/state, motor.m1..m4, deck.* flags (no deck attached), and the PID
 * position controller's z integral output posCtl.Zi with its gains posCtlPid.zKp/zKi (the vehicle model
 * integrates it, shim_set_position_integrator). */
#include <string.h>

#include "controller.h"
#include "log.h"
#include "param.h"
#include "polycc_shim.h"
#include "sim_internal.h"

static float attRoll, attPitch, attYaw, thrust;
/* motor.m1..m4 (PWM ratio, 0..65535): the firmware logs the mixed per-motor values; the shim has one
 * thrust, so all four report it (cfclient's flight tab reads them). */
static uint16_t motorRatio;
static uint8_t controllerParam = ControllerTypePID;
static uint8_t estimatorParam = 2; /* Kalman */
static uint8_t stopParam, enHighLevel, resetEstimation, infdmp;
static uint16_t landedTimeout = 1000u, supervisorInfo;
static float vbat = 4.0f;
static int8_t pmState;
static uint8_t deckNone;
static float posZi;                      /* m/s */
static float posZKp = 2.0f, posZKi = 0.5f; /* the firmware's PID_POS_Z_KP / KI */

void shimPlatformReset(void)
{
    attRoll = attPitch = attYaw = thrust = 0.0f;
    motorRatio = 0u;
    controllerParam = ControllerTypePID;
    estimatorParam = 2;
    stopParam = enHighLevel = resetEstimation = infdmp = 0;
    supervisorInfo = 0;
    posZi = 0.0f;
    posZKp = 2.0f;
    posZKi = 0.5f;
}

void shim_set_position_integrator(float zi)
{
    posZi = zi;
}

float shim_position_gain(int which)
{
    return which == 0 ? posZKp : posZKi;
}

void shim_set_attitude(float roll_deg, float pitch_deg, float yaw_deg, float thrust_cmd)
{
    attRoll = roll_deg;
    attPitch = pitch_deg;
    attYaw = yaw_deg;
    thrust = thrust_cmd;
    motorRatio = thrust_cmd <= 0.0f ? 0u : (thrust_cmd >= 65535.0f ? 65535u : (uint16_t)thrust_cmd);
    shimLogSetYaw(roll_deg, pitch_deg, yaw_deg);
}

static void controllerChanged(void)
{
    shim_set_controller(controllerParam == ControllerTypeAutoSelect ? ControllerTypePID : controllerParam);
    if (controllerParam == ControllerTypeOot) { /* the firmware's controllerInit() of the chosen controller */
        controllerOutOfTreeInit();
    }
}

LOG_GROUP_START(stabilizer)
LOG_ADD(LOG_FLOAT, roll, &attRoll)
LOG_ADD(LOG_FLOAT, pitch, &attPitch)
LOG_ADD(LOG_FLOAT, yaw, &attYaw)
LOG_ADD(LOG_FLOAT, thrust, &thrust)
LOG_GROUP_STOP(stabilizer)

LOG_GROUP_START(supervisor)
LOG_ADD(LOG_UINT16, info, &supervisorInfo)
LOG_GROUP_STOP(supervisor)

LOG_GROUP_START(posCtl)
LOG_ADD(LOG_FLOAT, Zi, &posZi)
LOG_GROUP_STOP(posCtl)

LOG_GROUP_START(motor)
LOG_ADD_CORE(LOG_UINT16, m1, &motorRatio)
LOG_ADD_CORE(LOG_UINT16, m2, &motorRatio)
LOG_ADD_CORE(LOG_UINT16, m3, &motorRatio)
LOG_ADD_CORE(LOG_UINT16, m4, &motorRatio)
LOG_GROUP_STOP(motor)

LOG_GROUP_START(pm)
LOG_ADD_CORE(LOG_FLOAT, vbat, &vbat)
LOG_ADD_CORE(LOG_INT8, state, &pmState)
LOG_GROUP_STOP(pm)

PARAM_GROUP_START(stabilizer)
PARAM_ADD_CORE(PARAM_UINT8, estimator, &estimatorParam)
PARAM_ADD_CORE_WITH_CALLBACK(PARAM_UINT8, controller, &controllerParam, &controllerChanged)
PARAM_ADD_CORE(PARAM_UINT8, stop, &stopParam)
PARAM_GROUP_STOP(stabilizer)

PARAM_GROUP_START(commander)
PARAM_ADD_CORE(PARAM_UINT8, enHighLevel, &enHighLevel)
PARAM_GROUP_STOP(commander)

PARAM_GROUP_START(kalman)
PARAM_ADD_CORE(PARAM_UINT8, resetEstimation, &resetEstimation)
PARAM_GROUP_STOP(kalman)

PARAM_GROUP_START(supervisor)
PARAM_ADD(PARAM_UINT8, infdmp, &infdmp)
PARAM_ADD(PARAM_UINT16, landedTimeout, &landedTimeout)
PARAM_GROUP_STOP(supervisor)

PARAM_GROUP_START(posCtlPid)
PARAM_ADD(PARAM_FLOAT | PARAM_PERSISTENT, zKp, &posZKp)
PARAM_ADD(PARAM_FLOAT | PARAM_PERSISTENT, zKi, &posZKi)
PARAM_GROUP_STOP(posCtlPid)

PARAM_GROUP_START(deck)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcFlow, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcZRanger, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcFlow2, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcZRanger2, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcMultiranger, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcLighthouse4, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcLoco, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcDWM1000, &deckNone)
PARAM_ADD_CORE(PARAM_UINT8 | PARAM_RONLY, bcAI, &deckNone)
PARAM_GROUP_STOP(deck)
