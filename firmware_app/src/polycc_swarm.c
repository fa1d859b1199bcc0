/*
 * polycc_swarm.c -- neighbour terms (buffered Voronoi half-spaces with an ageing buffer) in the
 * certified barrier; see polycc_swarm.h and docs/swarm.md.
 *
 * float32 only, -ffp-contract=off; every operation is mirrored in the same order by
 * polycc/onboard/swarm.py (tests/onboard/test_swarm_bitexact.py compares uint32 patterns).
 */
#include <math.h>
#include <string.h>

#include "polycc_swarm.h"

#define SW_ONE_MINUS 0.99999904632568359375f /* 1 - 2^-20 */
#define SW_MARGIN 3.814697265625e-06f        /* 2^-18 */
#define SW_FLOOR 0.0009765625f               /* 2^-10 m */
#define SW_D2_MIN 1.0e-12f                   /* m^2: coincident positions below this */

typedef char polycc_swarm_size_check[sizeof(((polycc_swarm_t *)0)->nbr) == POLYCC_SWARM_MAX * sizeof(polycc_nbr_t) ? 1 : -1];

static int sw_finite(float x)
{
    uint32_t b;
    memcpy(&b, &x, sizeof b);
    return ((b >> 23) & 0xffu) != 0xffu;
}

static int sw_coord_ok(float v)
{
    return sw_finite(v) && v >= -POLYCC_POS_MAX && v <= POLYCC_POS_MAX;
}

static float sw_abs(float x)
{
    return x < 0.0f ? -x : x;
}

void polycc_swarm_reset(polycc_swarm_t *sw)
{
    memset(sw, 0, sizeof *sw);
}

int polycc_swarm_report(polycc_swarm_t *sw, uint8_t id, const float p_j[3], uint32_t age_ms, float r_j,
                        const float p0[3])
{
    int i, k = -1;
    float d[3], d2, s, p1;
    polycc_nbr_t *nb;
    for (i = 0; i < 3; ++i) {
        if (!sw_coord_ok(p_j[i]) || !sw_coord_ok(p0[i])) {
            return -1;
        }
    }
    if (!sw_finite(r_j) || !(r_j >= 0.0f) || !(r_j <= POLYCC_SWARM_RADIUS_MAX)) {
        return -1;
    }
    for (i = 0; i < (int)POLYCC_SWARM_MAX; ++i) {
        if (sw->nbr[i].used && sw->nbr[i].id == id) {
            k = i;
            break;
        }
    }
    if (k < 0) {
        for (i = 0; i < (int)POLYCC_SWARM_MAX; ++i) {
            if (!sw->nbr[i].used) {
                k = i;
                break;
            }
        }
        if (k < 0) {
            return -1;
        }
        sw->count += 1u;
    }
    nb = &sw->nbr[k];
    for (i = 0; i < 3; ++i) {
        d[i] = p_j[i] - p0[i];
    }
    d2 = (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2];
    if (!(d2 >= SW_D2_MIN)) {
        nb->n[0] = 0.0f;
        nb->n[1] = 0.0f;
        nb->n[2] = 0.0f;
    } else {
        s = (1.0f / sqrtf(d2)) * SW_ONE_MINUS;
        for (i = 0; i < 3; ++i) {
            nb->n[i] = d[i] * s;
        }
    }
    nb->a = (nb->n[0] * p0[0] + nb->n[1] * p0[1]) + nb->n[2] * p0[2];
    p1 = (sw_abs(p_j[0]) + sw_abs(p_j[1])) + sw_abs(p_j[2]);
    nb->b = ((nb->n[0] * p_j[0] + nb->n[1] * p_j[1]) + nb->n[2] * p_j[2]) - SW_MARGIN * (p1 + SW_FLOOR);
    nb->r = r_j;
    nb->age_ms = age_ms > POLYCC_SWARM_AGE_MAX_MS ? POLYCC_SWARM_AGE_MAX_MS : age_ms;
    nb->id = id;
    nb->used = 1u;
    return k;
}

int polycc_swarm_forget(polycc_swarm_t *sw, uint8_t id)
{
    uint32_t i;
    for (i = 0; i < POLYCC_SWARM_MAX; ++i) {
        if (sw->nbr[i].used && sw->nbr[i].id == id) {
            memset(&sw->nbr[i], 0, sizeof sw->nbr[i]);
            sw->count -= 1u;
            return 1;
        }
    }
    return 0;
}

void polycc_swarm_age(polycc_swarm_t *sw, uint32_t dt_ms)
{
    uint32_t i;
    for (i = 0; i < POLYCC_SWARM_MAX; ++i) {
        polycc_nbr_t *nb = &sw->nbr[i];
        if (nb->used) {
            nb->age_ms = (POLYCC_SWARM_AGE_MAX_MS - nb->age_ms) < dt_ms ? POLYCC_SWARM_AGE_MAX_MS : nb->age_ms + dt_ms;
        }
    }
}

int polycc_swarm_stale(const polycc_swarm_t *sw, uint32_t timeout_ms)
{
    uint32_t i;
    for (i = 0; i < POLYCC_SWARM_MAX; ++i) {
        if (sw->nbr[i].used && sw->nbr[i].age_ms > timeout_ms) {
            return 1;
        }
    }
    return 0;
}

float polycc_swarm_term(const polycc_nbr_t *nb, float r, float v, const float p[3], int *ageing)
{
    float rho = r + nb->r;
    float tau = (float)nb->age_ms * 0.001f;
    float vt = v * tau;
    float fair = 0.5f * ((nb->a + nb->b) - rho);
    float aged = (nb->b - rho) - vt;
    float e, np, p1, mu;
    int ag = aged < fair;
    e = ag ? aged : fair;
    np = (nb->n[0] * p[0] + nb->n[1] * p[1]) + nb->n[2] * p[2];
    p1 = (sw_abs(p[0]) + sw_abs(p[1])) + sw_abs(p[2]);
    mu = SW_MARGIN * ((((p1 + sw_abs(nb->b)) + rho) + vt) + (sw_abs(e) + SW_FLOOR));
    *ageing = ag;
    return (e - np) - mu;
}

static void sw_zero(polycc_out_t *out, uint32_t flags)
{
    memset(out, 0, sizeof *out);
    out->flags = flags;
}

uint32_t polycc_swarm_step(const polycc_scene_t *scene, const polycc_params_t *params, const polycc_swarm_t *sw,
                           float v_nbr, const float x[3], const float goal[3], polycc_out_t *out)
{
    uint32_t flags = 0u, k;
    float c, S, G[3], Dacc, kappa, h, un[3], dot, viol, invS, D, psi;
    int i;
    if (sw->count == 0u) {
        return polycc_step(scene, params, x, goal, out);
    }
    if (polycc_step(scene, params, x, goal, out) & POLYCC_FLAG_INVALID) {
        return out->flags;
    }
    if (!sw_finite(v_nbr) || !(v_nbr >= 0.0f) || !(v_nbr <= POLYCC_SWARM_V_MAX)) {
        sw_zero(out, POLYCC_FLAG_INVALID);
        return out->flags;
    }
    /* the kernel's nominal, recomputed (its flags mix the nominal's and its own filter's saturation) */
    h = -0.5f * params->c_clf;
    for (i = 0; i < 3; ++i) {
        un[i] = h * (x[i] - goal[i]);
    }
    flags |= polycc_saturate(un, params->v_max);
    kappa = params->kappa;
    c = out->psi;
    S = 1.0f;
    G[0] = out->grad[0];
    G[1] = out->grad[1];
    G[2] = out->grad[2];
    Dacc = 0.0f;
    for (k = 0u; k < POLYCC_SWARM_MAX; ++k) {
        const polycc_nbr_t *nb = &sw->nbr[k];
        int ag;
        float dv;
        if (!nb->used) {
            continue;
        }
        h = polycc_swarm_term(nb, params->radius, v_nbr, x, &ag);
        dv = ag ? v_nbr : 0.0f;
        if (h < c) {
            float r = polycc_exp(kappa * (h - c));
            S = r * S + 1.0f;
            for (i = 0; i < 3; ++i) {
                G[i] = r * G[i] + -nb->n[i];
            }
            Dacc = r * Dacc + dv;
            c = h;
        } else {
            float xx = kappa * (c - h);
            if (xx > -POLYCC_NEGLIGIBLE_NATS) {
                float e = polycc_exp(xx);
                S = S + e;
                for (i = 0; i < 3; ++i) {
                    G[i] = G[i] + e * -nb->n[i];
                }
                Dacc = Dacc + e * dv;
            }
        }
    }
    psi = c - polycc_log(S) / kappa;
    invS = 1.0f / S;
    for (i = 0; i < 3; ++i) {
        out->grad[i] = G[i] * invS;
        out->u_nom[i] = un[i];
        out->u[i] = un[i];
    }
    D = Dacc * invS;
    out->psi = psi;
    dot = (out->grad[0] * un[0] + out->grad[1] * un[1]) + out->grad[2] * un[2];
    viol = (dot + params->beta * psi) - D;
    if (viol < 0.0f) {
        float g2 = (out->grad[0] * out->grad[0] + out->grad[1] * out->grad[1]) + out->grad[2] * out->grad[2];
        float lam;
        if (!(g2 >= POLYCC_GRAD2_MIN)) {
            sw_zero(out, POLYCC_FLAG_INVALID | POLYCC_FLAG_DEGENERATE);
            return out->flags;
        }
        lam = -viol / g2;
        for (i = 0; i < 3; ++i) {
            out->u[i] = out->u[i] + lam * out->grad[i];
        }
        flags |= POLYCC_FLAG_ACTIVE;
        flags |= polycc_saturate(out->u, params->v_max);
    }
    if (psi < 0.0f) {
        flags |= POLYCC_FLAG_INSIDE;
    }
    if (!sw_finite(psi)) {
        sw_zero(out, POLYCC_FLAG_INVALID);
        return out->flags;
    }
    for (i = 0; i < 3; ++i) {
        if (!sw_finite(out->u[i]) || !sw_finite(out->grad[i])) {
            sw_zero(out, POLYCC_FLAG_INVALID);
            return out->flags;
        }
    }
    out->flags = flags;
    return flags;
}
