/* Shim of crazyflie-firmware src/modules/interface/controller/controller.h (controller type query). */
#pragma once

typedef enum {
    ControllerTypeAutoSelect,
    ControllerTypePID,
    ControllerTypeMellinger,
    ControllerTypeINDI,
    ControllerTypeBrescianini,
    ControllerTypeLee,
    ControllerType_COUNT,
} ControllerType;

ControllerType controllerGetType(void);
const char *controllerGetName(void);
