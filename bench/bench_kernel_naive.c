/*
 * Naive paper-style barrier kernel, for the benchmark only (bench/bench_kernel.py).
 *
 * Every half-plane of every polytope, libm expf/logf, plain (max-shifted) log-sum-exp
 * soft-max per polytope and log-sum-exp soft-min over polytopes, then the same CLF and
 * closed-form CBF filter as polycc_step.  Not certified (the soft-max over-estimates), no
 * culling, no early exit.  Also holds main() of the benchmark ELF (never run by unicorn).
 */
#include <math.h>
#include <stdint.h>

#include "polycc_kernel.h"

#define NAIVE_MAX_POLYS 512

static float naive_a[NAIVE_MAX_POLYS];
static float naive_ga[NAIVE_MAX_POLYS][3];

static float naive_g(const polycc_scene_t *sc, const polycc_plane_t *pl, const float p[3])
{
    const polycc_normal_t *n = &sc->normals[pl->normal];
    return ((n->nx * p[0] + n->ny * p[1]) + n->nz * p[2]) - (float)pl->d * sc->quantum;
}

uint32_t naive_step(const polycc_scene_t *sc, const polycc_params_t *prm, const float x[3], const float goal[3],
                    polycc_out_t *out);

uint32_t naive_step(const polycc_scene_t *sc, const polycc_params_t *prm, const float x[3], const float goal[3],
                    polycc_out_t *out)
{
    uint32_t j, k, l, n = sc->n_polys < NAIVE_MAX_POLYS ? sc->n_polys : NAIVE_MAX_POLYS;
    float kappa = prm->kappa, amin = 3.0e38f, S2 = 0.0f, G[3] = {0.0f, 0.0f, 0.0f};
    float dot, viol, n2;
    int i;
    for (j = 0, k = 0; j < sc->n_clusters && k < n; ++j) {
      const polycc_plane_t *pl = &sc->planes[sc->clusters[j].first_plane];
      uint32_t kend = sc->clusters[j].first + sc->clusters[j].count;
      for (; k < kend && k < n; ++k) {
        uint32_t L = POLYCC_META_COUNT(sc->polys[k].meta);
        float m = -3.0e38f, S = 0.0f, N[3] = {0.0f, 0.0f, 0.0f};
        for (l = 0; l < L; ++l) {
            float g = naive_g(sc, &pl[l], x);
            m = g > m ? g : m;
        }
        for (l = 0; l < L; ++l) {
            const polycc_normal_t *nl = &sc->normals[pl[l].normal];
            float e = expf(kappa * (naive_g(sc, &pl[l], x) - m));
            S += e;
            N[0] += e * nl->nx;
            N[1] += e * nl->ny;
            N[2] += e * nl->nz;
        }
        naive_a[k] = m + logf(S) / kappa;
        for (i = 0; i < 3; ++i) {
            naive_ga[k][i] = N[i] / S;
        }
        amin = naive_a[k] < amin ? naive_a[k] : amin;
        pl += L;
      }
    }
    for (k = 0; k < n; ++k) {
        float e = expf(-kappa * (naive_a[k] - amin));
        S2 += e;
        for (i = 0; i < 3; ++i) {
            G[i] += e * naive_ga[k][i];
        }
    }
    out->psi = amin - logf(S2) / kappa - prm->radius;
    for (i = 0; i < 3; ++i) {
        out->grad[i] = G[i] / S2;
        out->u_nom[i] = -0.5f * prm->c_clf * (x[i] - goal[i]);
    }
    n2 = out->u_nom[0] * out->u_nom[0] + out->u_nom[1] * out->u_nom[1] + out->u_nom[2] * out->u_nom[2];
    if (n2 > prm->v_max * prm->v_max) {
        float s = prm->v_max / sqrtf(n2);
        for (i = 0; i < 3; ++i) {
            out->u_nom[i] *= s;
        }
    }
    dot = out->grad[0] * out->u_nom[0] + out->grad[1] * out->u_nom[1] + out->grad[2] * out->u_nom[2];
    viol = dot + prm->beta * out->psi;
    for (i = 0; i < 3; ++i) {
        out->u[i] = out->u_nom[i];
    }
    if (viol < 0.0f) {
        float g2 = out->grad[0] * out->grad[0] + out->grad[1] * out->grad[1] + out->grad[2] * out->grad[2];
        for (i = 0; i < 3; ++i) {
            out->u[i] -= viol / g2 * out->grad[i];
        }
    }
    out->flags = 0u;
    return 0u;
}

typedef uint32_t (*bench_step_fn)(const polycc_scene_t *, const polycc_params_t *, const float *, const float *,
                                   polycc_out_t *);
/* Referenced through a volatile table so that --gc-sections keeps both kernels. */
static volatile bench_step_fn bench_entry[2] = {polycc_step, naive_step};

int main(void)
{
    return bench_entry[0] == bench_entry[1];
}
