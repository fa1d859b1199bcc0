/*
 * polycc_app.h -- the polycc Crazyflie app: one control tick, callable on its own.
 *
 * appMain() (polycc_app.c) is polycc_app_init() followed by
 *     forever { period = polycc_app_tick(); vTaskDelayUntil(&last, period); }
 * The host SITL (polycc/sim/) compiles the same polycc_app.c against firmware API shims and
 * calls polycc_app_init() / polycc_app_tick() itself, one tick at a time.
 *
 * No firmware headers here: this file is shared with the host build.
 *
 * States (log polycc.status; polycc/onboard/app.py has the same names):
 *   While polycc.enable = 0 the app sends nothing.  When it is set, the app takes control only
 *   if the vehicle is flying (supervisor), the high-level commander has finished its takeoff
 *   or go_to, the PID controller is selected and the link is up; until then the status says
 *   what it waits for and nothing is sent (so enabling on the floor never spins the motors).
 *   While it has control ("engaged") it streams setpoints every tick at priority EXTRX: ground
 *   setpoints are ignored until disable.  A bad or stale estimate, psi < 0 or a kernel refusal
 *   holds the position where the fallback began.  Disabling, or a controller change, hands
 *   the vehicle to the high-level commander holding position (go_to to the stopping point,
 *   then commanderRelaxPriority), so a later go_to or land works; losing the link hands it to
 *   a high-level landing.  No path sends a stop (motors-off) setpoint.
 *
 *   The PID position controller ignores the velocity of position setpoints, so its z integral
 *   (log posCtl.Zi) winds up during every high-level takeoff or go_to (about zKi h / zKp for a
 *   climb of h) and is frozen while the app streams velocities; a later position hold then
 *   settles Zi/zKp away from its setpoint (8 cm after a 0.9 m takeoff in the firmware's SITL).
 *   So the app's position holds aim at z - Zi/zKp (a pure proportional hold at z), and after a
 *   disable in the air it keeps that hold until |Zi| < POLYCC_APP_SETTLE_ZI (Zi decays with
 *   zKp/zKi = 4 s) before it hands over (status 13); a high-level command from the ground
 *   (go_to, land) during that time takes over at once.
 */
#ifndef POLYCC_APP_H
#define POLYCC_APP_H

#include <stdint.h>

#include "polycc_kernel.h"

/* Log variable polycc.status (uint8). */
#define POLYCC_STATUS_DISABLED 0u       /* enable == 0: nothing sent (after a hand-over: the HL commander holds) */
#define POLYCC_STATUS_OK 1u             /* engaged: filtered velocity setpoint sent */
#define POLYCC_STATUS_NO_ESTIMATE 2u    /* stateEstimate.x/y/z not in the log TOC: holding position */
#define POLYCC_STATUS_BAD_ESTIMATE 3u   /* estimate NaN/Inf/out of range or its variance too large: holding */
#define POLYCC_STATUS_STALE_ESTIMATE 4u /* estimate bit-identical for POLYCC_APP_STALE_MS: holding */
#define POLYCC_STATUS_INSIDE 5u         /* psi < 0 (inside an inflated obstacle): holding position */
#define POLYCC_STATUS_KERNEL_INVALID 6u /* kernel refused params/goal/state (POLYCC_FLAG_INVALID): holding */
#define POLYCC_STATUS_NOT_FLYING 7u     /* enabled on the ground: nothing sent; take off first (high-level takeoff) */
#define POLYCC_STATUS_WAIT_HL 8u        /* enabled, waiting for the high-level commander's takeoff/go_to to finish */
#define POLYCC_STATUS_BAD_CONTROLLER 9u /* stabilizer.controller is not PID (1): enable refused, nothing sent */
#define POLYCC_STATUS_LINK_LOST 10u     /* no packet from the ground for POLYCC_APP_LINK_TIMEOUT_MS: handed over to
                                           a high-level landing, enable cleared */
#define POLYCC_STATUS_SUPERVISOR 11u    /* supervisor locked, crashed or tumbled: nothing sent */
#define POLYCC_STATUS_TOO_SLOW 12u      /* the scene's worst case does not fit even POLYCC_APP_MIN_RATE_HZ: refused */
#define POLYCC_STATUS_NEIGHBOUR_LOST 13u /* swarm: a neighbour's report is older than POLYCC_SWARM_TIMEOUT_MS, or
                                           fewer neighbours than param polycc.swarmN are known: holding position
                                           (docs/swarm.md) */
#define POLYCC_STATUS_HANDING_OVER 14u  /* disabled in the air: holding the hand-over point until the PID position
                                           controller's z integral has decayed (at most POLYCC_APP_SETTLE_MAX_MS; a
                                           high-level command takes over at once), then the high-level commander */
#define POLYCC_APP_STATUS_COUNT 15u

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
/* The kernel's certified worst case (POLYCC_SCENE_WORST_CYCLES of polytopes.h) may use at most
 * this share of a tick: the rate is lowered at init (and when rateHz is written) until it fits,
 * so a tick never overruns its period and the idle task (hardware watchdog) always runs. */
#define POLYCC_APP_CPU_SHARE_PERCENT 50u
#define POLYCC_APP_CPU_HZ 168000000u /* STM32F405 */

/* The estimate counts as stale when x, y and z keep exactly the same bits this long. */
#define POLYCC_APP_STALE_MS 250u
/* The estimate is refused when any of kalman.varX/varY/varZ exceeds this (m^2); the check
 * is skipped when those log variables do not exist (another estimator). */
#define POLYCC_APP_POS_VAR_MAX 0.01f
/* |stateEstimate component| above this (m) is refused. */
#define POLYCC_APP_POS_LIMIT 1000.0f

/* Link loss: crtpIsConnected() false (the radio link: no packet for 1 s), or, once the ground
 * has sent app-channel heartbeats (polycc fly sends them every 100 ms), none for this long. */
#define POLYCC_APP_LINK_TIMEOUT_MS 1000u
/* Hand-over to the high-level commander: go_to the point where a deceleration of
 * POLYCC_APP_HANDOVER_ACC stops the vehicle (at most half the clearance psi ahead), in at least
 * POLYCC_APP_HANDOVER_MIN_S.  Landing after link loss descends at POLYCC_APP_LAND_SPEED. */
#define POLYCC_APP_HANDOVER_ACC 2.0f   /* m/s^2 */
#define POLYCC_APP_HANDOVER_MIN_S 0.5f /* s */
#define POLYCC_APP_LAND_SPEED 0.3f     /* m/s */
#define POLYCC_APP_LAND_MIN_S 2.0f     /* s */
/* Hand-over after a disable in the air waits (holding) until |posCtl.Zi| is below this (m/s, i.e. at most
 * Zi/zKp = 1 cm of offset left) or for at most POLYCC_APP_SETTLE_MAX_MS. */
#define POLYCC_APP_SETTLE_ZI 0.02f
#define POLYCC_APP_SETTLE_MAX_MS 12000u
/* posCtlPid.zKp when that param is not found (the firmware's PID_POS_Z_KP), 1/s, and the largest
 * integral compensation applied to a hold, m. */
#define POLYCC_APP_POS_Z_KP 2.0f
#define POLYCC_APP_ZI_OFFSET_MAX 0.2f

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

/* The shield's keep-out (polycc_controller_keepout: polyccShield.radius + tube while it is on): the filter
 * flies with a radius r that starts at polycc.radius when an engagement starts (or after a tick that did not
 * evaluate the kernel) and rises towards max(polycc.radius, keep-out) only where the previous tick's
 * clearance psi + r exceeds the new radius by this slack (m; a 3 m/s vehicle moves 6 mm per 500 Hz tick).
 * So the app stops where the shield lets it instead of driving into the shield's margin and being braked
 * there, and a start inside the margin is not a psi < 0 hold: the vehicle flies, and the radius grows as it
 * leaves the margin. It never shrinks within an engagement, except to follow the two parameters down. */
#define POLYCC_APP_KEEPOUT_SLACK 0.02f

/* Swarm (docs/swarm.md): app-channel neighbour report, little-endian, 18 bytes: 'N', id (uint8),
 * x, y, z (float, m), age (uint16, ms: latency and estimate error / V), radius (uint16, mm). */
#define POLYCC_APP_NBR_MAGIC 0x4eu
#define POLYCC_APP_NBR_BYTES 18u
#define POLYCC_APP_NBR_FORGET 0xffffu /* age field: remove this neighbour (it landed or left) */
#define POLYCC_APP_DEFAULT_SWARM_V 1.0f /* m/s: param polycc.swarmV */
/* Swarm over the firmware's P2P radio broadcast (radiolink.h, docs/swarm.md): the same 18-byte record
 * is the payload of a P2P packet on this P2P port. A drone with param polycc.swarmId != 0 broadcasts its
 * own estimate every polycc.p2pMs ms with age polycc.p2pAgeMs (its estimate error / V + the radio's
 * latency bound); every drone takes the records it hears, whatever its own id, through a lock-free ring
 * of POLYCC_APP_P2P_RING records (the radio task writes, the app task reads), each aged from its arrival
 * tick. A P2P record never removes a neighbour (only the ground, which knows a drone is down, does). */
#define POLYCC_APP_P2P_PORT 0x0bu
#define POLYCC_APP_P2P_RING 16u
#define POLYCC_APP_DEFAULT_P2P_MS 50u     /* param polycc.p2pMs: 20 Hz */
#define POLYCC_APP_DEFAULT_P2P_AGE_MS 20u /* param polycc.p2pAgeMs */
/* Certified bound of polycc_swarm_step's extra cost over polycc_step with POLYCC_SWARM_MAX neighbours
 * (Cortex-M4F cycles, from its operation count; docs/swarm.md), added to the scene's worst case. */
#define POLYCC_APP_SWARM_WORST_CYCLES 6000u

/* App-channel reply to every packet from the ground (little-endian, 18 bytes, then up to 12
 * bytes of the request as an echo): status (uint8), enable (uint8), psi (float, m), x, y, z
 * (float, m, the estimate). */
#define POLYCC_APP_REPLY_BYTES 18u
/* Largest packet the app sends: the CRTP payload, CRTP_MAX_DATA_SIZE = 30 bytes. Firmware of 2024 (the
 * CrazySim SITL fork among it) defines APPCHANNEL_MTU as 31 while crtpSendPacketBlock() asserts
 * size <= 30, and assertFail() stops the motors and resets the Crazyflie: a 31-byte reply (18 + a
 * 13-byte echo of an 18-byte neighbour report) dropped the drone. Never size a packet by APPCHANNEL_MTU. */
#define POLYCC_APP_TX_MAX 30u

/* ---- for the shield (polycc_controller.c): the scene this app was built with ---- */
const polycc_scene_t *polycc_app_scene(void);
uint32_t polycc_app_scene_worst_cycles(void); /* POLYCC_SCENE_WORST_CYCLES of polytopes.h */
float polycc_app_scene_kappa(void);

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
    uint32_t handovers;      /* hand-overs to the high-level commander (hold) */
    uint32_t landings;       /* hand-overs to a high-level landing (link loss) */
    float handover[4];       /* the last hand-over's go_to target x, y, z (m) and duration (s) */
} polycc_app_trace_t;
const polycc_app_trace_t *polycc_app_trace(void);

#endif /* POLYCC_APP_H */
