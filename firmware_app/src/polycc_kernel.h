/*
 * polycc_kernel.h -- on-board barrier kernel: certified soft-min/soft-max polytope CBF,
 * CLF nominal controller and closed-form CBF safety filter (single integrator).
 *
 * Portable C99, float32 only, no firmware headers, no libm exp/log.
 *
 * REQUIRED COMPILER FLAG: -ffp-contract=off (no fused multiply-add).  The Python reference
 * (polycc/onboard/barrier.py) reproduces every float32 operation of this file in the same order;
 * fused operations would change the rounding and break bit-exactness.  sqrtf() is used and
 * is correctly rounded everywhere; add -fno-math-errno so it compiles to one VSQRT.
 *
 * Barrier (docs/barrier.md):
 *   psi(p) = softmin_k a_k(p) - r - margin(p),
 *   a_k(p) = sum_l w_kl g_kl(p),  w_kl = softmax_l(kappa g_kl(p))  (Boltzmann soft-max),
 * Certified: psi(p) + r <= min_k max_l g_kl(p) for every p, float32 rounding included.
 */
#ifndef POLYCC_KERNEL_H
#define POLYCC_KERNEL_H

#include <stdint.h>

#include "polycc_scene_layout.h"

#ifdef __cplusplus
extern "C" {
#endif

#define POLYCC_KERNEL_VERSION 1u

/* Soft-max / soft-min terms below exp(-POLYCC_NEGLIGIBLE_NATS) of the largest are skipped,
 * and a polytope is culled when its term is provably below that ratio. */
#define POLYCC_NEGLIGIBLE_NATS 17.0f
/* |position component| and |goal component| above this (metres) are invalid input. */
#define POLYCC_POS_MAX 1.0e5f
/* Valid range of kappa (1/m). */
#define POLYCC_KAPPA_MIN 1.0f
#define POLYCC_KAPPA_MAX 1.0e4f
/* The filter treats |grad psi|^2 below this as degenerate (no safe direction known). */
#define POLYCC_GRAD2_MIN 1.0e-12f
/* psi reported for a scene without polytopes. */
#define POLYCC_PSI_EMPTY 1.0e6f

/* Output flags (bitwise or). */
#define POLYCC_FLAG_ACTIVE 0x01u     /* the CBF filter changed u_nom */
#define POLYCC_FLAG_INSIDE 0x02u     /* psi < 0: the agent ball may touch an obstacle */
#define POLYCC_FLAG_INVALID 0x04u    /* NaN/Inf/out-of-range input, bad params/scene, or a
                                        degenerate state: every output is zero */
#define POLYCC_FLAG_SATURATED 0x08u  /* u_nom or u was scaled down to v_max */
#define POLYCC_FLAG_DEGENERATE 0x10u /* filter active but grad psi ~ 0 (set with INVALID) */

typedef struct polycc_params {
    float kappa;  /* soft-min/soft-max sharpness, 1/m (paper: 100) */
    float radius; /* agent radius r, m (>= 0) */
    float beta;   /* CBF class-K gain, 1/s (> 0) */
    float c_clf;  /* CLF decay rate c, 1/s (>= 0) */
    float v_max;  /* speed limit, m/s (> 0) */
} polycc_params_t;

typedef struct polycc_out {
    float u[3];     /* filtered velocity command, m/s */
    float u_nom[3]; /* saturated CLF nominal velocity, m/s */
    float psi;      /* certified barrier psi_r (metres); >= 0 keeps the agent ball clear */
    float grad[3];  /* analytic gradient of psi (the margin's 2^-20 slope is not included) */
    uint32_t flags; /* POLYCC_FLAG_* */
} polycc_out_t;

/* Fast exp for x <= 88.  exp(0) == 1 exactly; returns 0 for x < -87 (and NaN).
 * Relative error <= 3e-7 on [-87, 88] (measured: 2.54e-7; tests/test_kernel_fastmath.py). */
/* Scales v (m/s) in place to |v| <= vmax; POLYCC_FLAG_SATURATED if it did, else 0. */
uint32_t polycc_saturate(float v[3], float vmax);

float polycc_exp(float x);
/* Fast natural log for normal x > 0 (finite).  polycc_log(1) == 0 and polycc_log(x) >= 0
 * for x >= 1.  Absolute error <= 6e-7 on [1, 65536], relative <= 3e-7 above 1.001 (measured).
 * Neither error enters the certificate (docs/barrier.md), only the tightness. */
float polycc_log(float x);

/* Evaluates psi (radius and rounding margin already subtracted) and its gradient at p.
 * Returns 0 or POLYCC_FLAG_INVALID (then *psi = 0, grad = 0).
 * Stack: 292 bytes for polycc_step on the Cortex-M4 at -Os (tests/onboard/test_kernel_arm.py). */
uint32_t polycc_barrier(const polycc_scene_t *scene, const polycc_params_t *params, const float p[3],
                        float *psi, float grad[3]);

/* One control step at position x towards goal:
 *   u_nom = argmin 1/2|u|^2 s.t. grad V . u <= -c V, V = 1/2|x - goal|^2   (= -c/2 (x - goal))
 *   u_nom <- u_nom * min(1, v_max/|u_nom|)
 *   u = argmin 1/2|u - u_nom|^2 s.t. grad psi . u >= -beta psi  (closed form)
 *   u <- u * min(1, v_max/|u|)   (keeps the CBF constraint whenever psi >= 0)
 * Fills *out (never NaN) and returns out->flags. */
uint32_t polycc_step(const polycc_scene_t *scene, const polycc_params_t *params, const float x[3],
                     const float goal[3], polycc_out_t *out);

#ifdef __cplusplus
}
#endif

#endif /* POLYCC_KERNEL_H */
