/*
 * polycc_controller.h -- the shield mode of the polycc app: an out-of-tree controller
 * (CONFIG_CONTROLLER_OOT, stabilizer.controller = OutOfTree) that filters every setpoint through
 * the shield (polycc_shield.h) before the firmware's PID controller acts on it.
 *
 * No firmware headers here (shared with the host build).  World frame, z up; m, s, m/s.
 *
 * Two halves (docs/barrier.md section 8, "Rate and slot"):
 *   stabilizer task, every 1 kHz tick: controllerOutOfTree() -> polycc_controller_filter() posts the
 *     commander's setpoint (as a desired velocity) and the estimate to a mailbox, applies the
 *     current decision, then controllerPid() runs on the result.  O(1): no psi evaluation.
 *   app task, every app tick: polycc_controller_plan() makes a decision every
 *     POLYCC_SHIELD_PERIOD_TICKS (100 Hz, the PID position loop's rate) from the mailbox: one full
 *     polycc_shield_run() with as many psi evaluations as the scene's certified worst case fits in
 *     POLYCC_SHIELD_CPU_SHARE_PERCENT of the period.  The app task is preemptible, so a plan never
 *     delays the 1 kHz loop.
 * A decision planned from the estimate of tick t0 is flown from t0 + 10 to t0 + 30 (the model's
 * latency and commit, n_lat = 3, n_commit = 2 steps of 10 ms; its successor normally replaces it at
 * t0 + 20, so one late app tick is flown on its own certificate): certified -> the candidate (the
 * setpoint passes unchanged when the candidate is the desired velocity), otherwise the backup,
 * the brake policy (polycc_shield_brake, recomputed every tick from the live velocity estimate);
 * a decision not replaced in time is flown on until its successor is due if that successor is planned and
 * certified, not a backup or a landing (its plan modelled this command over its latency; counted in
 * bridged), else it expires into the backup (counted in expired).
 * Setpoints the shield changes become world-frame velocity setpoints (yaw fields kept).  Manual
 * attitude/rate/thrust setpoints (x, y or z mode disabled) pass unfiltered: status manual,
 * counted, one warning per switch-on.
 *
 * Param polyccShield.enable switches the shield; on: the first decision is flown one to two
 * periods later (status starting: setpoints pass meanwhile); off: deferred (status off-pending)
 * while the shield changes the setpoint: until the source's setpoint lies where the vehicle is (within
 * POLYCC_SHIELD_HANDBACK_GAP horizontally, position modes) and the shield passes it unchanged or the
 * vehicle is at rest and the source asks it to stay or to descend straight down (slower than
 * POLYCC_SHIELD_HOLD_SPEED).  A descent asked straight down is flown as a landing
 * (POLYCC_SHIELD_LAND_SPEED), so a landing with the shield on touches down.
 */
#ifndef POLYCC_CONTROLLER_H
#define POLYCC_CONTROLLER_H

#include <stdint.h>

#include "polycc_shield.h"

/* Log variable polyccShield.status (uint8). */
#define POLYCC_SHIELD_STATUS_OFF 0u         /* enable = 0: setpoints pass untouched */
#define POLYCC_SHIELD_STATUS_PASS 1u        /* certified, the setpoint passes unchanged */
#define POLYCC_SHIELD_STATUS_FILTERED 2u    /* certified candidate differs from the setpoint: deflected/slowed */
#define POLYCC_SHIELD_STATUS_BACKUP 3u      /* no certified plan: braking to hover (u = 0) */
#define POLYCC_SHIELD_STATUS_MANUAL 4u      /* attitude/rate/thrust setpoint: passed unfiltered (unprotected) */
#define POLYCC_SHIELD_STATUS_OFF_PENDING 5u /* enable = 0 while the shield changes the setpoint: still on */
#define POLYCC_SHIELD_STATUS_TOO_SLOW 6u    /* the scene's worst case does not fit a stabilizer tick: refused */
#define POLYCC_SHIELD_STATUS_STARTING 7u    /* just switched on: the first plan is being computed, setpoints pass */
#define POLYCC_SHIELD_STATUS_NO_CONTROLLER 8u /* enabled, but stabilizer.controller is not the out-of-tree one */
#define POLYCC_SHIELD_STATUS_LANDING 9u     /* a descent asked straight down: flown to touchdown */
#define POLYCC_SHIELD_STATUS_COUNT 10u

#define POLYCC_SHIELD_PERIOD_TICKS 10u /* 100 Hz decisions at the 1 kHz stabilizer tick */
/* Share of the CPU over one period (10 ms = 1 680 000 cycles) a plan may use, percent. */
#define POLYCC_SHIELD_CPU_SHARE_PERCENT 25u
/* Cycle model of the plan's own work besides psi (polycc/budget/cycle_model.py shield_plan_cycles). */
#define POLYCC_SHIELD_FIXED_CYCLES 4000u /* mailbox, candidate, decision, bookkeeping */
#define POLYCC_SHIELD_STEP_CYCLES 300u   /* one model step plus its share of the coverage walk (measured 236
                                          * before the brake policy; + its sqrt and divide, estimated) */

/* Defaults of the polyccShield parameter group. */
#define POLYCC_SHIELD_DEFAULT_TUBE 0.05f  /* m: model-tracking allowance e_tube */
#define POLYCC_SHIELD_DEFAULT_VMAX 3.0f   /* m/s: speed cap of the candidate */
#define POLYCC_SHIELD_DEFAULT_K1 4.0f     /* 1/s */
#define POLYCC_SHIELD_DEFAULT_K0 4.0f     /* 1/s^2 */
#define POLYCC_SHIELD_DEFAULT_PSI_CAP 0.0f /* m: polyccShield.psicap, clearance cap D on psi (0: off) */
#define POLYCC_SHIELD_DEFAULT_RADIUS 0.1f /* m: polyccShield.radius, the shield's own (polycc.radius is the app's) */
/* The closed-loop model's constants (polycc_shield_params_t; docs/barrier.md section 8). */
#define POLYCC_SHIELD_K_V 4.2803f   /* 1/s: PID_VEL_X_KP 25 deg per m/s times g */
#define POLYCC_SHIELD_TAU 0.25f     /* s: attitude loop 1/6 s made conservative for rate loop and motor lag */
#define POLYCC_SHIELD_A_XY 3.96f    /* m/s^2: tilt limit g tan 22 deg; the brake is commanded at it */
#define POLYCC_SHIELD_A_BRAKE 3.0f  /* m/s^2: the brake's deceleration as the model assumes it (< A_XY: the
                                     * velocity loop's integrator and the estimate's delay weaken it) */
#define POLYCC_SHIELD_N_LAT 3u      /* model steps: 20 ms estimator delay + the 10 ms until flown */
/* Model steps a decision's candidate is certified for before the brake: two periods, so a decision whose
 * successor comes up to one period late is flown on its own certificate instead of expiring into the brake
 * (docs/barrier.md section 8, "Rate and slot").  With 1, every app tick more than a period late was a brake
 * pulse: 17.6 expired ticks per 0.5 m/s flight in the real-firmware SITL; the one such event measured in
 * detail was a 2-3 m/s^2 step of the vertical acceleration (the brake's u_z = 0 against the app's descent). */
#define POLYCC_SHIELD_N_COMMIT 2u
/* Under the backup, below this speed (m/s) the brake becomes a position hold where it got that slow:
 * a velocity setpoint of 0 leaves the velocity loop's integrator to creep the vehicle on. */
#define POLYCC_SHIELD_HOLD_SPEED 0.1f
/* Switching off hands back only a position setpoint this close to the estimate (horizontal, m). */
#define POLYCC_SHIELD_HANDBACK_GAP 0.1f
/* Landing (docs/barrier.md section 8): when the shield would not pass the setpoint unchanged, the
 * source asks to go down faster than POLYCC_SHIELD_HOLD_SPEED and horizontally slower than it, and the
 * vehicle moves horizontally slower than it and not down faster than POLYCC_SHIELD_LAND_SPEED +
 * POLYCC_SHIELD_HOLD_SPEED, the decision is a landing: the horizontal position held where it began, the
 * source's vertical setpoint flown as sent (capped at LAND_SPEED down), until the source stops the
 * motors.  As sent, not slowed: the high-level commander stops the motors when its land trajectory ends,
 * wherever the vehicle is, so a landing that lagged it would end in a drop.  Without the landing, the
 * shield held the vehicle radius + tube above the floor (or beside a box, where a descent is not
 * certified either) and it dropped from there when the motors stopped. */
#define POLYCC_SHIELD_LAND_SPEED 1.0f /* m/s: the PID position loop's own limit (POLYCC_SHIELD_POS_VMAX) */
/* At the tube's edge (psi < tube + this, m), a plan for a desired velocity within 60 deg of psi's gradient
 * keeps psi >= last psi - this instead of >= tube (floor 0): a vehicle held at psi = tube can leave. */
#define POLYCC_SHIELD_ESCAPE_DEPTH 0.005f
/* The stock PID's position loop as the shield predicts it (position_controller_pid.c): under a position
 * setpoint its velocity command is kp (setpoint - estimate) plus the integral output (posCtl.Zi in z; the x, y
 * integral gains are 0 by default), limited to xVelMax * velMaxOverhead = 1 m/s * 1.10; the setpoint's own
 * velocity is not fed forward (posCtlPid kp 2 1/s). */
#define POLYCC_SHIELD_POS_KP 2.0f
#define POLYCC_SHIELD_POS_VMAX 1.1f
/* A live setpoint passes unchanged under a "pass" decision only while its desired velocity stays
 * within this of the one the decision certified (m/s, per component). */
#define POLYCC_SHIELD_PASS_TOL 0.05f

/* Resets the shield (off) and its parameters to the defaults. */
void polycc_controller_init(void);
/* Stabilizer side: replaces *sp by what the PID gets this tick.  pos/vel/acc: the estimate (m,
 * m/s, m/s^2), yaw_deg its heading; tick: the FreeRTOS tick count (1 kHz; not stabilizerStep, which
 * starts at 1 after calibration), the clock of polycc_controller_plan()'s now. */
struct setpoint_s;
void polycc_controller_filter(struct setpoint_s *sp, const float pos[3], const float vel[3], const float acc[3],
                              float yaw_deg, uint32_t tick);
/* App side: plans a decision when one is due (call every app tick; now = FreeRTOS tick). */
void polycc_controller_plan(uint32_t now);
/* psi evaluations per plan the scene's certified worst case allows (0: the shield is refused). */
uint32_t polycc_controller_max_evals(void);
/* Certified worst case of one plan, Cortex-M4 cycles (cycle model; <= the period's share). */
uint32_t polycc_controller_plan_worst_cycles(void);
/* The shield's keep-out, m: polyccShield.radius + polyccShield.tube while polyccShield.enable is set, else 0.
 * The go-to-goal app's radius rises to this as its clearance allows (polycc_app.h POLYCC_APP_KEEPOUT_SLACK), so
 * that its own filter stops where the shield lets it, instead of driving into the shield's margin. */
float polycc_controller_keepout(void);

/* Hooks into the app (polycc_app.c) for the PID's z integral: posCtl.Zi, m/s (0 when the PID cascade does
 * not fly the setpoints or the variable is missing), and the offset Zi / zKp (m, capped) a position hold's z
 * subtracts so that the PID holds where the hold says. */
float polycc_app_pid_zi(void);
float polycc_app_pid_zi_offset(void);

/* Counters and the last decision (log group polyccShield; for tests and the SITL). */
typedef struct polycc_controller_trace {
    uint32_t decisions;   /* decisions made while on */
    uint32_t certified;   /* certified plans flown (pass or filtered) */
    uint32_t backups;     /* decisions that flew the backup (brake) */
    uint32_t infeasible;  /* ECBF half-space infeasible within v_max */
    uint32_t manual;      /* ticks with a manual setpoint passed unfiltered */
    uint32_t eval_caps;   /* plans not covered within their evaluations */
    uint32_t overrides;   /* ticks the setpoint was replaced */
    uint32_t landings;    /* decisions flown as a landing */
    uint32_t escapes;     /* plans made with the tube lowered to leave its edge */
    uint32_t bridged;     /* ticks a decision was flown past its end, up to its late certified successor */
    uint32_t expired;     /* ticks braked because a decision ran out with no certified successor planned */
    uint32_t last_flags;  /* POLYCC_SHIELD_* of the last finished plan */
    uint32_t last_evals;
    float last_min_c;     /* m */
    float psi;            /* psi at the last decision's estimate, m */
    float u[3];           /* the velocity flown under the current decision, m/s */
    uint8_t status;       /* POLYCC_SHIELD_STATUS_* */
    uint8_t on;
} polycc_controller_trace_t;
const polycc_controller_trace_t *polycc_controller_trace(void);
/* The last plan (its modelled path, flags, inputs in job->in; for tests and diagnostics). */
const polycc_shield_job_t *polycc_controller_job(void);

#endif /* POLYCC_CONTROLLER_H */
