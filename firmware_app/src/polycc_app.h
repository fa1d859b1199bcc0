/*
 * polycc_app.h -- the polycc Crazyflie app: one control tick, callable on its own.
 *
 * appMain() (polycc_app.c) is polycc_app_init() followed by
 *     forever { period = polycc_app_tick(); vTaskDelayUntil(&last, period); }
 * The host SITL (polycc/sim/) compiles the same polycc_app.c against firmware API shims and
 * calls polycc_app_init() / polycc_app_tick() itself, one tick at a time.
 *
 * No firmware headers here: this file is shared with the host build.
 */
#ifndef POLYCC_APP_H
#define POLYCC_APP_H

#include <stdint.h>

#include "polycc_kernel.h"

/* Log variable polycc.status (uint8). */
#define POLYCC_STATUS_DISABLED 0u       /* enable == 0: no setpoints sent, priority relaxed */
#define POLYCC_STATUS_OK 1u             /* flying: filtered velocity setpoint sent */
#define POLYCC_STATUS_NO_ESTIMATE 2u    /* stateEstimate.x/y/z not found in the log TOC: zero velocity */
#define POLYCC_STATUS_BAD_ESTIMATE 3u   /* estimate NaN/Inf/out of range or its variance too large: zero velocity */
#define POLYCC_STATUS_STALE_ESTIMATE 4u /* estimate bit-identical for POLYCC_APP_STALE_MS: zero velocity */
#define POLYCC_STATUS_INSIDE 5u         /* psi < 0 (inside an inflated obstacle): zero velocity */
#define POLYCC_STATUS_KERNEL_INVALID 6u /* kernel refused params/goal/state (POLYCC_FLAG_INVALID): zero velocity */

/* Defaults of the polycc parameter group. */
#define POLYCC_APP_DEFAULT_RATE_HZ 500u
#define POLYCC_APP_DEFAULT_VMAX 0.5f    /* m/s */
#define POLYCC_APP_DEFAULT_BETA 1.0f    /* 1/s */
#define POLYCC_APP_DEFAULT_CLF_GAIN 2.0f /* 1/s: u_nom = -(clfGain/2)(x - goal) */
#define POLYCC_APP_DEFAULT_RADIUS 0.1f  /* m: Crazyflie 2.1 with propellers fits in a 0.1 m ball */
#define POLYCC_APP_DEFAULT_GOAL_Z 1.0f  /* m (goalX = goalY = 0) */

/* rateHz below this is raised to it, so that setpoints arrive at least every 100 ms and the
 * commander's 500 ms watchdog never fires while enabled. */
#define POLYCC_APP_MIN_RATE_HZ 10u

/* The estimate counts as stale when x, y and z keep exactly the same bits this long. */
#define POLYCC_APP_STALE_MS 250u
/* The estimate is refused when any of kalman.varX/varY/varZ exceeds this (m^2); the check
 * is skipped when those log variables do not exist (another estimator). */
#define POLYCC_APP_POS_VAR_MAX 0.01f
/* |stateEstimate component| above this (m) is refused. */
#define POLYCC_APP_POS_LIMIT 1000.0f

/* Braking term (closes the realization gap of a lagging vehicle, bench/bench_sim.py): the
 * kernel's speed limit is min(vmax, s(psi)), s(psi) the largest speed from which the vehicle
 * stops within the previous tick's clearance psi when it reacts after POLYCC_APP_BRAKE_S and
 * decelerates at POLYCC_APP_BRAKE_ACC (t s + s^2 / (2 A) = psi), at least POLYCC_APP_BRAKE_VMIN.
 * The single-integrator CBF bounds only the approach to the nearest obstacle; this bounds the
 * speed towards every obstacle.  POLYCC_APP_BRAKE_ACC = 0 disables it. */
#ifndef POLYCC_APP_BRAKE_S
/* s: attitude lag (1/6 s) + motor lag (~50 ms) + estimator delay (20 ms) + velocity-loop
 * period (10 ms), rounded up; 0.2 s still let the rigid-body quadrotor model collide at 2 m/s */
#define POLYCC_APP_BRAKE_S 0.3f
#endif
#ifndef POLYCC_APP_BRAKE_ACC
#define POLYCC_APP_BRAKE_ACC 3.9f /* m/s^2: g tan(22 deg), the stock controller's tilt limit */
#endif
#define POLYCC_APP_BRAKE_VMIN 0.05f /* m/s */

/* Resets the app's state and parameters to their defaults and looks up the log variables. */
void polycc_app_init(void);
/* One iteration of the control loop; returns the delay (FreeRTOS ticks, >= 1) until the next. */
uint32_t polycc_app_tick(void);

/* The last kernel call: its inputs and output (for tests and the SITL; not used on board). */
typedef struct polycc_app_trace {
    uint32_t calls;          /* kernel calls since polycc_app_init */
    float x[3], goal[3];     /* state and goal given to polycc_step */
    polycc_params_t params;  /* params given to polycc_step (v_max includes the braking term) */
    polycc_out_t out;        /* its output */
} polycc_app_trace_t;
const polycc_app_trace_t *polycc_app_trace(void);

#endif /* POLYCC_APP_H */
