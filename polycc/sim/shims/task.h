/* Shim of the FreeRTOS task API used by apps. */
#pragma once

#ifndef INC_FREERTOS_H
#include "FreeRTOS.h"
#endif

TickType_t xTaskGetTickCount(void);
void vTaskDelay(const TickType_t xTicksToDelay);
void vTaskDelayUntil(TickType_t *const pxPreviousWakeTime, const TickType_t xTimeIncrement);

/* Critical sections (the host is single-threaded per app instance: no-ops). */
#define taskENTER_CRITICAL() ((void)0)
#define taskEXIT_CRITICAL() ((void)0)
