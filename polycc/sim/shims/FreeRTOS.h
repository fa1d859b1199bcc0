/* Shim of the FreeRTOS kernel types and the Crazyflie FreeRTOSConfig.h time macros (1 kHz tick). */
#pragma once

#include <stdint.h>

typedef uint32_t TickType_t;
typedef long BaseType_t;
typedef unsigned long UBaseType_t;
#define portTickType TickType_t

#define pdFALSE ((BaseType_t)0)
#define pdTRUE ((BaseType_t)1)

#define configTICK_RATE_HZ_RAW 1000
#define configTICK_RATE_HZ ((portTickType)configTICK_RATE_HZ_RAW)
#define pdMS_TO_TICKS(xTimeInMs) ((TickType_t)(((TickType_t)(xTimeInMs) * (TickType_t)configTICK_RATE_HZ) / (TickType_t)1000U))

#define M2T(X) ((unsigned int)(X))
#define F2T(X) ((unsigned int)((configTICK_RATE_HZ / (X))))
#define T2M(X) ((unsigned int)(X))
#define S2T(X) ((portTickType)((X) * configTICK_RATE_HZ))
#define T2S(X) ((X) / (float)configTICK_RATE_HZ)
