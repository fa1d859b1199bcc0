/* Shim of the Crazyflie config.h: the task priorities apps read (values of src/config/config.h). */
#pragma once

#define CMD_HIGH_LEVEL_TASK_PRI 2 /* the high-level commander's task */
#define SHIM_APP_TASK_PRI 1       /* the app's task: app-config CONFIG_APP_PRIORITY */
