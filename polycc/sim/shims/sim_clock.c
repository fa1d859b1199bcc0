/* Host FreeRTOS tick clock and usecTimestamp: simulated time, never sleeps. */
#include "FreeRTOS.h"
#include "config.h"
#include "polycc_shim.h"
#include "sim_internal.h"
#include "task.h"
#include "usec_time.h"

static TickType_t tick;
static uint64_t usecNow;
static uint32_t usecSection;
static UBaseType_t taskPriority = SHIM_APP_TASK_PRI;

void shim_reset(void)
{
    tick = 0u;
    usecNow = 0u;
    usecSection = 0u;
    taskPriority = SHIM_APP_TASK_PRI;
    shimLogReset();
    shimCommanderReset();
    shimDebugReset();
    shimAppchannelReset();
    shimPlatformReset();
    shimRadiolinkReset();
}

void shim_set_tick(uint32_t t)
{
    tick = t;
}

uint32_t shim_get_tick(void)
{
    return tick;
}

void shim_set_usec(uint64_t now_us, uint32_t section_us)
{
    usecNow = now_us;
    usecSection = section_us;
}

TickType_t xTaskGetTickCount(void)
{
    return tick;
}

void vTaskDelay(const TickType_t xTicksToDelay)
{
    tick += xTicksToDelay;
}

/* Wakes at *prev + inc (or now, if that is already past) and advances *prev. */
void vTaskDelayUntil(TickType_t *const pxPreviousWakeTime, const TickType_t xTimeIncrement)
{
    TickType_t wake = *pxPreviousWakeTime + xTimeIncrement;
    if ((int32_t)(wake - tick) > 0) {
        tick = wake;
    }
    *pxPreviousWakeTime = wake;
}

void usecTimerInit(void)
{
}

void usecTimerReset(void)
{
    usecNow = 0u;
}

uint64_t usecTimestamp(void)
{
    uint64_t t = usecNow;
    usecNow += usecSection;
    usecSection = 0u;
    return t;
}

UBaseType_t uxTaskPriorityGet(const TaskHandle_t xTask)
{
    (void)xTask;
    return taskPriority;
}

void vTaskPrioritySet(TaskHandle_t xTask, UBaseType_t uxNewPriority)
{
    (void)xTask;
    taskPriority = uxNewPriority;
    shimHlTaskRun();
}

unsigned long shimTaskPriority(void)
{
    return taskPriority;
}
