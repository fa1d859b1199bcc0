/*
 * polycc_shield.h -- velocity-aware safety shield on the certified barrier psi (docs/barrier.md, section 8).
 *
 * A backup CBF in gatekeeper form: a candidate velocity command (an exponential CBF through the
 * PID velocity loop) is flown only if the closed-loop model, simulated from the estimate through
 * the latency, one period of the candidate and then braking to hover, stays certified clear of
 * every stored polytope: sphere tracing with psi (a certified lower bound of the clearance; the
 * true clearance is 1-Lipschitz).  Otherwise the backup (u = 0, brake) is flown.
 *
 * World frame, z up; metres, seconds.  Portable C99, float32 only, no firmware headers, no libm
 * exp/log (psi comes from polycc_barrier).  REQUIRED: -ffp-contract=off; polycc/onboard/shield.py
 * reproduces every float32 operation of polycc_shield.c in the same order (bit-exact).
 *
 * Work can be split across stabilizer ticks: polycc_shield_plan() simulates the model and
 * evaluates psi once (at the estimate), each polycc_shield_advance() evaluates psi at most once
 * more; polycc_shield_run() does everything at once.  The result does not depend on the split.
 */
#ifndef POLYCC_SHIELD_H
#define POLYCC_SHIELD_H

#include <stdint.h>

#include "polycc_kernel.h"

#ifdef __cplusplus
extern "C" {
#endif

#define POLYCC_SHIELD_MAX_STEPS 200u /* model steps in the horizon (2 s at 10 ms) */
#define POLYCC_SHIELD_MAX_EVALS 32u  /* psi evaluations per plan */
/* |velocity|, |acceleration| and |command| components above this (m/s, m/s^2) are invalid input. */
#define POLYCC_SHIELD_VA_MAX 100.0f
/* Relative slack on summed chord lengths (covers float32 summation, docs/barrier.md section 8). */
#define POLYCC_SHIELD_LEN_SLACK 1.0e-4f

/* Result flags (bitwise or). */
#define POLYCC_SHIELD_CERTIFIED 0x01u  /* the plan (candidate for one period, then brake) is certified */
#define POLYCC_SHIELD_ACTIVE 0x02u     /* the candidate differs from the desired velocity (ECBF or speed cap) */
#define POLYCC_SHIELD_INFEASIBLE 0x04u /* the ECBF half-space has no solution within v_max (or grad ~ 0) */
#define POLYCC_SHIELD_INVALID 0x08u    /* NaN/Inf/out-of-range input or params, kernel refusal at the estimate */
#define POLYCC_SHIELD_NO_STOP 0x10u    /* the model does not come to hover within the horizon */
#define POLYCC_SHIELD_BLOCKED 0x20u    /* a sample's psi is below the tube or a pair of samples does not overlap */
#define POLYCC_SHIELD_EVAL_CAP 0x40u   /* max_evals reached before the path was covered */
#define POLYCC_SHIELD_DONE 0x80u       /* the plan is decided (certified or not) */
#define POLYCC_SHIELD_SATURATED 0x100u /* the desired velocity was scaled down to v_max */

typedef struct polycc_shield_params {
    float kappa;    /* the scene's soft-min/soft-max sharpness, 1/m */
    float radius;   /* agent radius r, m (psi has it subtracted) */
    float h;        /* model step, s (the PID velocity loop: 0.01) */
    float k_v;      /* horizontal velocity-loop gain, 1/s */
    float k_z;      /* vertical velocity-loop gain, 1/s */
    float a_xy;     /* horizontal acceleration limit (tilt limit), m/s^2 */
    float a_up;     /* upward acceleration limit (full thrust), m/s^2 */
    float a_dn;     /* downward acceleration limit (thrust floor), m/s^2 (> 0) */
    float tau;      /* attitude/thrust lag time constant, s (>= h) */
    float k1;       /* ECBF gain on d psi/dt, 1/s */
    float k0;       /* ECBF gain on psi, 1/s^2 */
    float v_max;    /* speed cap of the candidate, m/s */
    float tube;     /* model-tracking allowance e_tube, m */
    float v_term;   /* terminal speed for "hover", m/s */
    float a_term;   /* terminal acceleration for "hover", m/s^2 */
    float a_brake;  /* horizontal deceleration of the brake policy, m/s^2 (<= a_xy; see polycc_shield_brake) */
    float psi_cap;  /* clearance cap D, m (0: off): every psi the shield uses is min(psi, D), its gradient
                     * zeroed when capped -- a flat but still certified lower bound (a spatial index's) */
    uint32_t n_lat;     /* model steps flown under u_app first (estimator delay + decision latency) */
    uint32_t n_commit;  /* model steps under the candidate, then the brake */
    uint32_t n_steps;   /* horizon, model steps (<= POLYCC_SHIELD_MAX_STEPS) */
    uint32_t max_evals; /* psi evaluations allowed (1..POLYCC_SHIELD_MAX_EVALS) */
} polycc_shield_params_t;

typedef struct polycc_shield_job {
    float x[201][3]; /* model positions x_0 = p .. x_n (POLYCC_SHIELD_MAX_STEPS + 1 rows) */
    float lam[201];  /* summed chord lengths from x_0 */
    float in[4][3];  /* the inputs p, v, a0, u_app (kept for polycc_shield_simulate) */
    float u_c[3];    /* candidate velocity command, m/s */
    float u_d[3];    /* desired velocity after the v_max cap, m/s */
    float a_end[3];  /* model acceleration after n_lat + n_commit steps (diagnostic) */
    float psi;       /* psi at the estimate, m */
    float grad[3];   /* its gradient */
    float c;         /* psi - tube at the current sample */
    float min_c;     /* smallest psi - tube over the samples, m */
    uint32_t n;      /* last model index */
    uint32_t i;      /* current sample index */
    uint32_t cov;    /* last index covered by the current sample */
    uint32_t evals;  /* psi evaluations so far */
    uint32_t flags;  /* POLYCC_SHIELD_* */
} polycc_shield_job_t;
_Static_assert(sizeof(((polycc_shield_job_t *)0)->lam) == (POLYCC_SHIELD_MAX_STEPS + 1u) * 4u, "MAX_STEPS + 1 rows");

/* Validates, evaluates psi at p, builds the candidate, simulates the model and covers what the
 * first sample covers.  p, v: estimate (m, m/s); a0: acceleration (m/s^2); u_app: the velocity
 * command flown during the latency; u_d: the desired velocity.  Returns job->flags. */
uint32_t polycc_shield_plan(polycc_shield_job_t *job, const polycc_scene_t *scene, const polycc_shield_params_t *prm,
                            const float p[3], const float v[3], const float a0[3], const float u_app[3],
                            const float u_d[3]);
/* polycc_shield_plan in two halves, for two stabilizer ticks: begin validates, evaluates psi at p and
 * builds the candidate; simulate runs the model and covers what the first sample covers (no psi
 * evaluation).  plan == begin, then simulate unless begin decided already. */
uint32_t polycc_shield_begin(polycc_shield_job_t *job, const polycc_scene_t *scene, const polycc_shield_params_t *prm,
                             const float p[3], const float v[3], const float a0[3], const float u_app[3],
                             const float u_d[3]);
uint32_t polycc_shield_simulate(polycc_shield_job_t *job, const polycc_shield_params_t *prm);
/* At most one more psi evaluation; returns job->flags (DONE once decided). */
uint32_t polycc_shield_advance(polycc_shield_job_t *job, const polycc_scene_t *scene,
                               const polycc_shield_params_t *prm);
/* The brake policy (the backup), world frame: u_z = 0 and horizontally u = v - min(|v_xy|, e) v_xy/|v_xy|
 * with e = a_brake / k_v: the PID velocity loop sees a velocity error of at most e against the
 * motion, k_v e = a_brake <= a_xy, so it stays inside the tilt limits in any direction (the
 * firmware clips roll and pitch separately: a saturated u = 0 turns an oblique brake).  v: the
 * velocity estimate, m/s; e: m/s. */
void polycc_shield_brake(float u[3], const float v[3], float e);
/* plan, then advance until done. */
uint32_t polycc_shield_run(polycc_shield_job_t *job, const polycc_scene_t *scene, const polycc_shield_params_t *prm,
                           const float p[3], const float v[3], const float a0[3], const float u_app[3],
                           const float u_d[3]);

#ifdef __cplusplus
}
#endif

#endif /* POLYCC_SHIELD_H */
