/*
 * polycc_shield.c -- velocity-aware safety shield (polycc_shield.h; derivation: docs/barrier.md section 8).
 *
 * Float32 only, -ffp-contract=off; polycc/onboard/shield.py mirrors every operation in this order.
 * sqrtf is correctly rounded (one VSQRT with -fno-math-errno); psi comes from polycc_barrier.
 */
#include <math.h>
#include <string.h>

#include "polycc_shield.h"

static int sh_in(float x, float lo, float hi)
{
    return x >= lo && x <= hi; /* false for NaN */
}

static int sh_vec_ok(const float *x, float lim)
{
    return sh_in(x[0], -lim, lim) && sh_in(x[1], -lim, lim) && sh_in(x[2], -lim, lim);
}

static int sh_params_ok(const polycc_shield_params_t *q)
{
    return sh_in(q->kappa, POLYCC_KAPPA_MIN, POLYCC_KAPPA_MAX) && sh_in(q->radius, 0.0f, POLYCC_POS_MAX) &&
           sh_in(q->h, 1.0e-4f, 0.1f) && sh_in(q->k_v, 1.0e-3f, 1.0e3f) && sh_in(q->k_z, 1.0e-3f, 1.0e3f) &&
           sh_in(q->a_xy, 1.0e-3f, 1.0e3f) && sh_in(q->a_up, 1.0e-3f, 1.0e3f) && sh_in(q->a_dn, 1.0e-3f, 1.0e3f) &&
           sh_in(q->tau, q->h, 10.0f) && sh_in(q->k1, 0.0f, 1.0e3f) && sh_in(q->k0, 0.0f, 1.0e4f) &&
           sh_in(q->v_max, 1.0e-3f, POLYCC_SHIELD_VA_MAX) && sh_in(q->tube, 0.0f, 10.0f) &&
           sh_in(q->v_term, 0.0f, 10.0f) && sh_in(q->a_term, 0.0f, 100.0f) &&
           sh_in(q->a_brake, 1.0e-3f, q->a_xy) && sh_in(q->psi_cap, 0.0f, POLYCC_POS_MAX) && q->n_steps >= 1u &&
           q->n_steps <= POLYCC_SHIELD_MAX_STEPS && q->n_lat <= q->n_steps && q->n_commit <= q->n_steps - q->n_lat &&
           q->max_evals >= 1u && q->max_evals <= POLYCC_SHIELD_MAX_EVALS;
}

static void sh_kernel_params(const polycc_shield_params_t *q, polycc_params_t *kp)
{
    kp->kappa = q->kappa;
    kp->radius = q->radius;
    kp->beta = 1.0f; /* unused by polycc_barrier, but must be valid */
    kp->c_clf = 0.0f;
    kp->v_max = 1.0f;
}

/* psi at p through the kernel, capped at psi_cap (min(psi, D) stays a certified lower bound; its
 * gradient is zero where capped).  Returns the kernel's flags. */
static uint32_t sh_psi(const polycc_scene_t *scene, const polycc_shield_params_t *q, const float p[3], float *psi,
                       float grad[3])
{
    polycc_params_t kp;
    uint32_t fl;
    sh_kernel_params(q, &kp);
    fl = polycc_barrier(scene, &kp, p, psi, grad);
    if (q->psi_cap > 0.0f && *psi > q->psi_cap) {
        *psi = q->psi_cap;
        grad[0] = grad[1] = grad[2] = 0.0f;
    }
    return fl;
}

static float sh_dot(const float *a, const float *b)
{
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2];
}

/* Last model index j >= i whose summed chord length from x_i (with slack) is <= c. */
static uint32_t sh_cover(const polycc_shield_job_t *job, uint32_t i, float c)
{
    uint32_t j = i;
    while (j < job->n) {
        float L = (job->lam[j + 1u] - job->lam[i]) + POLYCC_SHIELD_LEN_SLACK * job->lam[j + 1u];
        if (!(L <= c)) {
            break;
        }
        ++j;
    }
    return j;
}

static void sh_candidate(polycc_shield_job_t *job, const polycc_shield_params_t *q, const float v[3],
                         const float u_d[3])
{
    const float *g = job->grad;
    float ud[3], uc[3], g2, gv, b, gu;
    int k;
    ud[0] = u_d[0];
    ud[1] = u_d[1];
    ud[2] = u_d[2];
    if (polycc_saturate(ud, q->v_max) != 0u) {
        job->flags |= POLYCC_SHIELD_SATURATED;
    }
    memcpy(job->u_d, ud, sizeof ud);
    memcpy(uc, ud, sizeof uc);
    g2 = sh_dot(g, g);
    gv = sh_dot(g, v);
    b = gv - (q->k1 * gv + q->k0 * job->psi) / q->k_v;
    gu = sh_dot(g, ud);
    if (gu < b) {
        job->flags |= POLYCC_SHIELD_ACTIVE;
        if (!(g2 >= POLYCC_GRAD2_MIN)) {
            job->flags |= POLYCC_SHIELD_INFEASIBLE;
            uc[0] = uc[1] = uc[2] = 0.0f;
        } else {
            float lam = (b - gu) / g2;
            for (k = 0; k < 3; ++k) {
                uc[k] = ud[k] + lam * g[k];
            }
            (void)polycc_saturate(uc, q->v_max);
            if (sh_dot(g, uc) < b) {
                job->flags |= POLYCC_SHIELD_INFEASIBLE;
            }
        }
    }
    memcpy(job->u_c, uc, sizeof uc);
}

void polycc_shield_brake(float u[3], const float v[3], float e)
{
    float n2 = v[0] * v[0] + v[1] * v[1];
    u[0] = 0.0f;
    u[1] = 0.0f;
    u[2] = 0.0f;
    if (n2 > e * e) {
        float s = e / sqrtf(n2);
        u[0] = v[0] - s * v[0];
        u[1] = v[1] - s * v[1];
    }
}

/* The closed-loop model: n_lat steps of u_app, n_commit of u_c, then the brake policy. */
static void sh_simulate(polycc_shield_job_t *job, const polycc_shield_params_t *q, const float p[3],
                        const float v0[3], const float a0[3], const float u_app[3])
{
    const float eb = q->a_brake / q->k_v;
    const float g = q->h / q->tau, h = q->h, a2max = q->a_xy * q->a_xy, adn = -q->a_dn;
    const uint32_t n1 = q->n_lat, n2 = q->n_lat + q->n_commit;
    float v[3], a[3];
    uint32_t k;
    int i;
    memcpy(v, v0, sizeof v);
    memcpy(a, a0, sizeof a);
    memcpy(job->a_end, a0, sizeof a);
    memcpy(job->x[0], p, 3u * sizeof(float));
    job->lam[0] = 0.0f;
    for (k = 0u; k < q->n_steps; ++k) {
        const float *u = k < n1 ? u_app : job->u_c;
        float d[3], s[3], m2, ub[3];
        if (k >= n2) {
            polycc_shield_brake(ub, v, eb);
            u = ub;
        }
        d[0] = q->k_v * (u[0] - v[0]);
        d[1] = q->k_v * (u[1] - v[1]);
        m2 = d[0] * d[0] + d[1] * d[1];
        if (m2 > a2max) {
            float sc = q->a_xy / sqrtf(m2);
            d[0] = d[0] * sc;
            d[1] = d[1] * sc;
        }
        d[2] = q->k_z * (u[2] - v[2]);
        if (d[2] > q->a_up) {
            d[2] = q->a_up;
        }
        if (d[2] < adn) {
            d[2] = adn;
        }
        for (i = 0; i < 3; ++i) {
            a[i] = a[i] + g * (d[i] - a[i]);
            v[i] = v[i] + h * a[i];
            s[i] = h * v[i];
            job->x[k + 1u][i] = job->x[k][i] + s[i];
        }
        job->lam[k + 1u] = job->lam[k] + sqrtf(sh_dot(s, s));
        if (k + 1u == n2) {
            memcpy(job->a_end, a, sizeof a);
        }
    }
    job->n = q->n_steps;
    if (!(sh_dot(v, v) <= q->v_term * q->v_term) || !(sh_dot(a, a) <= q->a_term * q->a_term)) {
        job->flags |= POLYCC_SHIELD_NO_STOP | POLYCC_SHIELD_DONE;
    }
}

uint32_t polycc_shield_begin(polycc_shield_job_t *job, const polycc_scene_t *scene, const polycc_shield_params_t *prm,
                             const float p[3], const float v[3], const float a0[3], const float u_app[3],
                             const float u_d[3])
{
    uint32_t fl;
    job->flags = 0u;
    job->evals = 0u;
    job->n = 0u;
    job->i = 0u;
    job->cov = 0u;
    job->psi = 0.0f;
    job->c = 0.0f;
    job->min_c = 0.0f;
    memset(job->grad, 0, sizeof job->grad);
    memset(job->u_c, 0, sizeof job->u_c);
    memset(job->u_d, 0, sizeof job->u_d);
    memset(job->a_end, 0, sizeof job->a_end);
    memcpy(job->x[0], p, 3u * sizeof(float));
    job->lam[0] = 0.0f;
    memcpy(job->in[0], p, sizeof job->in[0]);
    memcpy(job->in[1], v, sizeof job->in[1]);
    memcpy(job->in[2], a0, sizeof job->in[2]);
    memcpy(job->in[3], u_app, sizeof job->in[3]);
    if (!sh_params_ok(prm) || !sh_vec_ok(p, POLYCC_POS_MAX) || !sh_vec_ok(v, POLYCC_SHIELD_VA_MAX) ||
        !sh_vec_ok(a0, POLYCC_SHIELD_VA_MAX) || !sh_vec_ok(u_app, POLYCC_SHIELD_VA_MAX) ||
        !sh_vec_ok(u_d, POLYCC_SHIELD_VA_MAX)) {
        job->flags = POLYCC_SHIELD_INVALID | POLYCC_SHIELD_DONE;
        return job->flags;
    }
    fl = sh_psi(scene, prm, p, &job->psi, job->grad);
    job->evals = 1u;
    if (fl & POLYCC_FLAG_INVALID) {
        job->psi = 0.0f;
        job->flags = POLYCC_SHIELD_INVALID | POLYCC_SHIELD_DONE;
        return job->flags;
    }
    sh_candidate(job, prm, v, u_d);
    return job->flags;
}

uint32_t polycc_shield_simulate(polycc_shield_job_t *job, const polycc_shield_params_t *prm)
{
    if (job->flags & POLYCC_SHIELD_DONE) {
        return job->flags;
    }
    sh_simulate(job, prm, job->in[0], job->in[1], job->in[2], job->in[3]);
    job->c = job->psi - prm->tube;
    job->min_c = job->c;
    if (job->flags & POLYCC_SHIELD_DONE) {
        return job->flags;
    }
    if (!(job->c >= 0.0f)) {
        job->flags |= POLYCC_SHIELD_BLOCKED | POLYCC_SHIELD_DONE;
        return job->flags;
    }
    job->cov = sh_cover(job, 0u, job->c);
    if (job->cov == job->n) {
        job->flags |= POLYCC_SHIELD_CERTIFIED | POLYCC_SHIELD_DONE;
    }
    return job->flags;
}

uint32_t polycc_shield_plan(polycc_shield_job_t *job, const polycc_scene_t *scene, const polycc_shield_params_t *prm,
                            const float p[3], const float v[3], const float a0[3], const float u_app[3],
                            const float u_d[3])
{
    (void)polycc_shield_begin(job, scene, prm, p, v, a0, u_app, u_d);
    return polycc_shield_simulate(job, prm);
}

uint32_t polycc_shield_advance(polycc_shield_job_t *job, const polycc_scene_t *scene,
                               const polycc_shield_params_t *prm)
{
    float psi, grad[3], cj, L;
    uint32_t j, fl;
    if (job->flags & POLYCC_SHIELD_DONE) {
        return job->flags;
    }
    if (job->evals >= prm->max_evals) {
        job->flags |= POLYCC_SHIELD_EVAL_CAP | POLYCC_SHIELD_DONE;
        return job->flags;
    }
    j = job->cov > job->i ? job->cov : job->i + 1u;
    fl = sh_psi(scene, prm, job->x[j], &psi, grad);
    job->evals += 1u;
    if (fl & POLYCC_FLAG_INVALID) {
        job->flags |= POLYCC_SHIELD_BLOCKED | POLYCC_SHIELD_DONE;
        return job->flags;
    }
    cj = psi - prm->tube;
    if (cj < job->min_c) {
        job->min_c = cj;
    }
    L = (job->lam[j] - job->lam[job->i]) + POLYCC_SHIELD_LEN_SLACK * job->lam[j];
    if (!(cj >= 0.0f) || !(L <= job->c + cj)) {
        job->flags |= POLYCC_SHIELD_BLOCKED | POLYCC_SHIELD_DONE;
        return job->flags;
    }
    job->i = j;
    job->c = cj;
    job->cov = sh_cover(job, j, cj);
    if (job->cov == job->n) {
        job->flags |= POLYCC_SHIELD_CERTIFIED | POLYCC_SHIELD_DONE;
    }
    return job->flags;
}

uint32_t polycc_shield_run(polycc_shield_job_t *job, const polycc_scene_t *scene, const polycc_shield_params_t *prm,
                           const float p[3], const float v[3], const float a0[3], const float u_app[3],
                           const float u_d[3])
{
    (void)polycc_shield_plan(job, scene, prm, p, v, a0, u_app, u_d);
    while (!(job->flags & POLYCC_SHIELD_DONE)) {
        (void)polycc_shield_advance(job, scene, prm);
    }
    return job->flags;
}
