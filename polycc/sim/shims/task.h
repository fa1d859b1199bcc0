/* Shim of the FreeRTOS task API used by apps. */
#pragma once

#ifndef INC_FREERTOS_H
#include "FreeRTOS.h"
#endif

TickType_t xTaskGetTickCount(void);
void vTaskDelay(const TickType_t xTicksToDelay);
void vTaskDelayUntil(TickType_t *const pxPreviousWakeTime, const TickType_t xTimeIncrement);

/* The calling task's priority (xTask NULL: the app's task; it starts at CONFIG_APP_PRIORITY, 1).  Setting it
 * is a preemption point: below CMD_HIGH_LEVEL_TASK_PRI, a high-level command queued by the test is carried out
 * there, as the firmware's high-level commander task would (sim_commander.c). */
typedef void *TaskHandle_t;
UBaseType_t uxTaskPriorityGet(const TaskHandle_t xTask);
void vTaskPrioritySet(TaskHandle_t xTask, UBaseType_t uxNewPriority);

/* Critical sections (the host is single-threaded per app instance: no-ops). */
#define taskENTER_CRITICAL() ((void)0)
#define taskEXIT_CRITICAL() ((void)0)
