/* Shim of crazyflie-firmware src/modules/interface/controller/controller.h (controller type query). */
#pragma once

#include "stabilizer_types.h"

/* The host build always has the out-of-tree controller (the firmware: CONFIG_CONTROLLER_OOT=y). */
#ifndef CONFIG_CONTROLLER_OOT
#define CONFIG_CONTROLLER_OOT 1
#endif

typedef enum {
    ControllerTypeAutoSelect,
    ControllerTypePID,
    ControllerTypeMellinger,
    ControllerTypeINDI,
    ControllerTypeBrescianini,
    ControllerTypeLee,
    ControllerTypeOot,
    ControllerType_COUNT,
} ControllerType;

ControllerType controllerGetType(void);
const char *controllerGetName(void);

/* The out-of-tree controller the app provides (the host stabilizer step calls it when selected). */
void controllerOutOfTreeInit(void);
bool controllerOutOfTreeTest(void);
void controllerOutOfTree(control_t *control, const setpoint_t *setpoint, const sensorData_t *sensors, const state_t *state,
                         const stabilizerStep_t stabilizerStep);
