/*
 * polycc_swarm.h -- neighbours in the on-board barrier: buffered Voronoi cell (BVC) half-spaces
 * with an ageing buffer, soft-min combined with the kernel's certified obstacle barrier.
 *
 * Portable C99, float32 only, no firmware headers, no libm exp/log (the kernel's polycc_exp/log).
 * REQUIRED: -ffp-contract=off (bit-exact with polycc/onboard/swarm.py).  Derivation, assumptions
 * and what stays certified: docs/swarm.md.  Metres, seconds, world frame.
 *
 * Per neighbour j (reported position p_j, radius r_j, age tau_j), own radius r, own estimate p0
 * when the report arrived:
 *   n = unit(p_j - p0) * (1 - 2^-20), a = n.p0, b = n.p_j - 2^-18 (|p_j|_1 + 2^-10), rho = r + r_j
 *   e = min((a + b - rho) / 2, (b - rho) - V tau),  h_j(p) = (e - n.p) - mu(p)
 * h_j(p) >= 0 implies |p - p_j(t)| >= rho whenever |p_j(t) - p_j| <= V tau (docs/swarm.md).
 * Psi = softmin_kappa(psi, h_1, ..., h_m) <= min(psi, min_j h_j).
 */
#ifndef POLYCC_SWARM_H
#define POLYCC_SWARM_H

#include <stdint.h>

#include "polycc_kernel.h"

#ifdef __cplusplus
extern "C" {
#endif

#define POLYCC_SWARM_MAX 16u          /* neighbour table size */
#define POLYCC_SWARM_TIMEOUT_MS 500u  /* a neighbour older than this: hold position */
#define POLYCC_SWARM_AGE_MAX_MS 60000u /* ages saturate here (the term only grows more conservative) */
#define POLYCC_SWARM_RADIUS_MAX 10.0f /* m: larger neighbour radii are refused */
#define POLYCC_SWARM_V_MAX 100.0f     /* m/s: larger speed bounds are refused */

typedef struct polycc_nbr {
    float n[3];      /* unit normal towards the neighbour, |n| <= 1 */
    float a, b;      /* n.p0 and a lower bound of n.p_j, m */
    float r;         /* neighbour radius, m */
    uint32_t age_ms; /* age of the report, ms (its stated latency, then counted up) */
    uint8_t id;
    uint8_t used;
    uint8_t pad[2];
} polycc_nbr_t;

typedef struct polycc_swarm {
    polycc_nbr_t nbr[16]; /* POLYCC_SWARM_MAX (a literal for the cffi declarations; checked in the .c) */
    uint32_t count; /* used entries */
} polycc_swarm_t;

/* Empties the table. */
void polycc_swarm_reset(polycc_swarm_t *sw);
/* Stores neighbour id's report (position p_j, m; age_ms; radius r_j, m) seen from the own estimate
 * p0.  Returns the slot, or -1 (nothing stored) for non-finite or out-of-range input or a full table. */
int polycc_swarm_report(polycc_swarm_t *sw, uint8_t id, const float p_j[3], uint32_t age_ms, float r_j,
                        const float p0[3]);
/* Removes neighbour id from the table (a drone that landed or left); returns 1 if it was there.
 * Its certificate is dropped with it: only the ground, which knows the drone is down, sends this. */
int polycc_swarm_forget(polycc_swarm_t *sw, uint8_t id);
/* Adds dt_ms to every age (saturating at POLYCC_SWARM_AGE_MAX_MS). */
void polycc_swarm_age(polycc_swarm_t *sw, uint32_t dt_ms);
/* 1 if some neighbour is older than timeout_ms. */
int polycc_swarm_stale(const polycc_swarm_t *sw, uint32_t timeout_ms);
/* h_j at p for neighbour slot k with own radius r and speed bound v (m/s); *ageing = 1 when the
 * ageing branch is the minimum. */
float polycc_swarm_term(const polycc_nbr_t *nb, float r, float v, const float p[3], int *ageing);
/* One control step: polycc_step() when the table is empty (bit-identical); otherwise the kernel's
 * psi and grad soft-min combined with every neighbour term, and the closed-form filter
 *   u = argmin |u - u_nom|^2 s.t. grad Psi . u >= -beta Psi + D   (D: ageing drift, docs/swarm.md)
 * then saturated to v_max.  out->psi = Psi, out->grad = grad Psi.  Returns out->flags. */
uint32_t polycc_swarm_step(const polycc_scene_t *scene, const polycc_params_t *params, const polycc_swarm_t *sw,
                           float v_nbr, const float x[3], const float goal[3], polycc_out_t *out);

#ifdef __cplusplus
}
#endif

#endif /* POLYCC_SWARM_H */
