/*
 * polycc_kernel.c -- see polycc_kernel.h.  Build with -ffp-contract=off (required).
 *
 * Every float32 operation below is mirrored, in the same order, by polycc/onboard/barrier.py;
 * change both together.  The derivations are in docs/barrier.md.
 */
#include "polycc_kernel.h"

#include <math.h> /* sqrtf only: correctly rounded (IEEE 754) on every target */
#include <string.h> /* memcpy of 4 bytes (bit casts), inlined by the compiler */

/* 2^-18: relative rounding margin (docs/barrier.md, "Never optimistic"). */
#define POLYCC_MARGIN_REL 0x1p-18f

/*
 * Speed hints that do not change any result.  GCC for ARM merges a*b + c into VMLA, which
 * rounds twice like the separate operations (so it is bit-identical) but issues in 3 cycles
 * on the Cortex-M4 instead of 2; POLYCC_OPAQUE pins the product in a VFP register so that
 * the multiply and the add stay separate.  Other compilers/targets: no-ops.
 */
#if defined(__GNUC__) && defined(__arm__) && defined(__ARM_FP) && !defined(POLYCC_NO_ASM_HINTS)
#define POLYCC_OPAQUE(x) __asm__("" : "+t"(x))
#else
#define POLYCC_OPAQUE(x) ((void)0)
#endif
#if defined(__GNUC__)
#define POLYCC_UNLIKELY(c) __builtin_expect(!!(c), 0)
#define POLYCC_NOINLINE __attribute__((noinline))
#define POLYCC_INLINE static inline __attribute__((always_inline))
#else
#define POLYCC_UNLIKELY(c) (c)
#define POLYCC_NOINLINE
#define POLYCC_INLINE static inline
#endif

POLYCC_INLINE float polycc_mul(float a, float b)
{
    float r = a * b;
    POLYCC_OPAQUE(r);
    return r;
}

static uint32_t polycc_bits(float x)
{
    uint32_t b;
    memcpy(&b, &x, sizeof b);
    return b;
}

static float polycc_from_bits(uint32_t b)
{
    float x;
    memcpy(&x, &b, sizeof x);
    return x;
}

/* 1 when x is finite (exponent field not all ones). */
static int polycc_finite(float x)
{
    return (polycc_bits(x) & 0x7f800000u) != 0x7f800000u;
}

/* exp for x <= 88 (the kernel only passes x <= 0); 0 below -87 and for NaN. */
POLYCC_INLINE float polycc_exp_le88(float x)
{
    float t, kf, r, p;
    int32_t k;
    if (POLYCC_UNLIKELY(!(x >= -87.0f))) {
        return 0.0f;
    }
    /* k = round(x / ln 2) by the 1.5 * 2^23 trick (round to nearest even, |t| < 2^22). */
    t = x * 1.44269502f;
    kf = (t + 12582912.0f) - 12582912.0f;
    /* Cody-Waite: ln2_hi has 16 significant bits, so kf * ln2_hi is exact for |k| <= 128. */
    r = (x - polycc_mul(kf, 0.693145751953125f)) - polycc_mul(kf, 1.42860677e-06f);
    /* exp(r) on |r| <= 0.347: degree-6 Taylor, Horner. */
    p = 0.00833333377f + polycc_mul(r, 0.00138888892f);
    p = 0.0416666679f + polycc_mul(r, p);
    p = 0.166666672f + polycc_mul(r, p);
    p = 0.5f + polycc_mul(r, p);
    p = 1.0f + polycc_mul(r, p);
    p = 1.0f + polycc_mul(r, p);
    k = (int32_t)kf;
    return p * polycc_from_bits((uint32_t)(k + 127) << 23);
}

float polycc_exp(float x)
{
    return polycc_exp_le88(x > 88.0f ? 88.0f : x);
}

/* g = n . p - d q in the order ((nx px + ny py) + nz pz) - d q; d q is exact (int16 times a
 * power of two). */
POLYCC_INLINE float polycc_plane_value(const polycc_plane_t *pl, const polycc_normal_t *nrm, float q, float px,
                                       float py, float pz)
{
    const polycc_normal_t *n = &nrm[pl->normal];
    return ((polycc_mul(n->nx, px) + polycc_mul(n->ny, py)) + polycc_mul(n->nz, pz)) - polycc_mul((float)pl->d, q);
}

/* u = p - c and |u|^2 in the order (ux^2 + uy^2) + uz^2, for a cluster (float32 centre). */
POLYCC_INLINE float polycc_dist2c(const polycc_cluster_t *C, float px, float py, float pz)
{
    float ux = px - C->cx, uy = py - C->cy, uz = pz - C->cz;
    return (polycc_mul(ux, ux) + polycc_mul(uy, uy)) + polycc_mul(uz, uz);
}

/* The same for a polytope, whose centre is stored in quanta (decoded exactly: c * q). */
POLYCC_INLINE float polycc_dist2u(const polycc_poly_t *P, float q, float px, float py, float pz, float u[3])
{
    u[0] = px - (float)P->c[0] * q;
    u[1] = py - (float)P->c[1] * q;
    u[2] = pz - (float)P->c[2] * q;
    return (polycc_mul(u[0], u[0]) + polycc_mul(u[1], u[1])) + polycc_mul(u[2], u[2]);
}

float polycc_log(float x)
{
    uint32_t b = polycc_bits(x);
    int32_t e = (int32_t)((b >> 23) & 0xffu) - 127;
    uint32_t mb = (b & 0x007fffffu) | 0x3f800000u; /* mantissa in [1, 2) */
    float f, s, z, w, ef;
    if (mb > 0x3fb504f3u) {                        /* > sqrt(2): use f/2 in [0.707, 1) */
        mb -= 0x00800000u;
        e += 1;
    }
    f = polycc_from_bits(mb);
    s = (f - 1.0f) / (f + 1.0f);
    z = s * s;
    /* log(f) = 2 atanh(s) = s (2 + 2/3 z + 2/5 z^2 + 2/7 z^3 + 2/9 z^4), |s| <= 0.1716. */
    w = s * (2.0f + z * (0.666666687f + z * (0.400000006f + z * (0.285714298f + z * 0.222222224f))));
    ef = (float)e;
    return ef * 0.693145751953125f + (w + ef * 1.42860677e-06f);
}

/* First plane in [pl, end) with g(p) > thr (its g in *g_out), or end.  The hot loop of the
 * kernel (about 16 instructions per half-plane at -Os): kept out of line and unrolled by two
 * so that skipping a negligible plane costs no call and half a loop branch. */
static POLYCC_NOINLINE const polycc_plane_t *polycc_scan(const polycc_plane_t *pl, const polycc_plane_t *end,
                                                         const polycc_normal_t *nrm, float q, float px, float py,
                                                         float pz, float thr, float *g_out)
{
    for (; pl + 1 < end; pl += 2) {
        float g0 = polycc_plane_value(pl, nrm, q, px, py, pz);
        float g1 = polycc_plane_value(pl + 1, nrm, q, px, py, pz);
        if (POLYCC_UNLIKELY(g0 > thr)) {
            *g_out = g0;
            return pl;
        }
        if (POLYCC_UNLIKELY(g1 > thr)) {
            *g_out = g1;
            return pl + 1;
        }
    }
    if (pl < end) {
        float g0 = polycc_plane_value(pl, nrm, q, px, py, pz);
        if (g0 > thr) {
            *g_out = g0;
            return pl;
        }
    }
    return end;
}

/*
 * Boltzmann soft-max of one polytope: a = sum_l w_l g_l with w = softmax(kappa g), and its
 * gradient (docs/barrier.md).  One scan: the lead plane (the one facing the query's octant)
 * first, then the others in plane order, so that a far polytope is usually dropped after one
 * plane.  Accumulators are relative to the running maximum m:
 *   S = sum e_l, A = sum e_l d_l, N = sum e_l n_l, M = sum e_l d_l n_l,
 *   d_l = g_l - m <= 0, e_l = exp(kappa d_l),
 * and are rescaled by exp(kappa (m_old - m_new)) when m grows.  Terms with
 * g_l <= m - NEGLIGIBLE/kappa are skipped.  The polytope is dropped (returns 0) as soon as the
 * running maximum reaches abort_at: then max_l g_l >= abort_at and it cannot matter to the
 * soft-min ("Culling").  Finally a = m + A/S and grad a = (N + kappa (M - (A/S) N)) / S.
 */
static int polycc_softmax_poly(const polycc_plane_t *base, uint32_t n, uint32_t lead, const polycc_normal_t *nrm,
                               float q, float px, float py, float pz, float kappa, float neg_cut, float abort_at,
                               float *a_out, float ga[3])
{
    const polycc_plane_t *lp = base + lead;
    const polycc_plane_t *pl = base, *end = lp; /* planes [0, lead), then (lead, n) */
    const polycc_normal_t *ln = &nrm[lp->normal];
    float m = polycc_plane_value(lp, nrm, q, px, py, pz);
    float thr, S, A, Nx, Ny, Nz, Mx, My, Mz, invS, qa;
    int second = 0;
    if (m >= abort_at) {
        return 0;
    }
    thr = m + neg_cut;
    S = 1.0f;
    A = 0.0f;
    Nx = ln->nx;
    Ny = ln->ny;
    Nz = ln->nz;
    Mx = 0.0f;
    My = 0.0f;
    Mz = 0.0f;
    for (;; ++pl) {
        float g;
        const polycc_normal_t *nl;
        pl = polycc_scan(pl, end, nrm, q, px, py, pz, thr, &g);
        if (pl >= end) {
            if (second) {
                break;
            }
            second = 1;
            pl = lp;
            end = base + n;
            continue;
        }
        nl = &nrm[pl->normal];
        if (g > m) {
            float d0, r;
            if (g >= abort_at) {
                return 0;
            }
            d0 = m - g;
            r = polycc_exp_le88(kappa * d0);
            A = r * (A + d0 * S);
            Mx = r * (Mx + d0 * Nx);
            My = r * (My + d0 * Ny);
            Mz = r * (Mz + d0 * Nz);
            S = r * S + 1.0f;
            Nx = r * Nx + nl->nx;
            Ny = r * Ny + nl->ny;
            Nz = r * Nz + nl->nz;
            m = g;
            thr = m + neg_cut;
        } else {
            float d = g - m;
            float e = polycc_exp_le88(kappa * d);
            float ed = e * d;
            S = S + e;
            A = A + ed;
            Nx = Nx + e * nl->nx;
            Ny = Ny + e * nl->ny;
            Nz = Nz + e * nl->nz;
            Mx = Mx + ed * nl->nx;
            My = My + ed * nl->ny;
            Mz = Mz + ed * nl->nz;
        }
    }
    invS = 1.0f / S;
    qa = A * invS;
    *a_out = m + qa;
    ga[0] = (Nx + kappa * (Mx - qa * Nx)) * invS;
    ga[1] = (Ny + kappa * (My - qa * Ny)) * invS;
    ga[2] = (Nz + kappa * (Mz - qa * Nz)) * invS;
    return 1;
}

static int polycc_params_ok(const polycc_params_t *prm)
{
    return prm != NULL && prm->kappa >= POLYCC_KAPPA_MIN && prm->kappa <= POLYCC_KAPPA_MAX &&
           prm->radius >= 0.0f && prm->radius <= POLYCC_POS_MAX && prm->beta > 0.0f && prm->beta <= 1.0e6f &&
           prm->c_clf >= 0.0f && prm->c_clf <= 1.0e6f && prm->v_max > 0.0f && prm->v_max <= 1.0e3f;
}

/* q is a power of two in [2^-20, 2^4]: mantissa bits zero, biased exponent in [107, 131]. */
static int polycc_quantum_ok(float q)
{
    uint32_t b = polycc_bits(q), e = b >> 23;
    return (b & 0x007fffffu) == 0u && e >= 107u && e <= 131u;
}

/* |v| <= POLYCC_POS_MAX for a finite v (false for NaN and +-Inf). */
static int polycc_coord_ok(float v)
{
    return v >= -POLYCC_POS_MAX && v <= POLYCC_POS_MAX;
}

static int polycc_scene_ok(const polycc_scene_t *sc)
{
    return sc != NULL && sc->format == POLYCC_SCENE_FORMAT &&
           (sc->n_polys == 0u) == (sc->n_clusters == 0u) &&
           (sc->n_clusters == 0u ||
            (sc->clusters != NULL && sc->polys != NULL && sc->planes != NULL && sc->normals != NULL)) &&
           polycc_quantum_ok(sc->quantum) && sc->coord_bound >= 0.0f && sc->coord_bound <= 1.0e6f &&
           sc->log_lmax >= 0.0f && sc->log_lmax <= 12.0f &&
           (sc->index == NULL ||
            (sc->n_polys > 0u && sc->index->cap > 0.0f && sc->index->cap <= 1.0e6f && sc->index->inv_cell > 0.0f &&
             sc->index->inv_cell <= 1.0e6f && polycc_coord_ok(sc->index->ox) && polycc_coord_ok(sc->index->oy) &&
             polycc_coord_ok(sc->index->oz) && sc->index->nx > 0u && sc->index->ny > 0u && sc->index->nz > 0u));
}


/* Culling test with d2 = |p - c|^2, Tp = max(T, 0): returns 1 when |p - c| > r_out + Tp * inv_gamma,
 * which proves max_l g_kl(p) > T for every polytope k the record bounds (docs/barrier.md,
 * "Culling").  Polytope records pass their decoded (exact) radii. */
POLYCC_INLINE int polycc_culled(float r_out, float inv_gamma, float d2, float Tp)
{
    float rad = r_out + Tp * inv_gamma;
    return d2 > rad * rad;
}

/* Online soft-min state of polycc_barrier (pass 2). */
typedef struct polycc_smin {
    float cur, S2, G[3], a_ref, slack, T, Tp;
    uint32_t nev;
} polycc_smin_t;

/* Pass 2 for one polytope (record P, planes from base): cull by its sphere, Boltzmann soft-max,
 * online soft-min update.  Out of line: shared by the cluster walk and the index walk. */
static POLYCC_NOINLINE void polycc_visit(const polycc_poly_t *P, const polycc_plane_t *base, const polycc_normal_t *nrm,
                                         float q, float q_out, const float p[3], float kappa, float neg_cut,
                                         polycc_smin_t *s)
{
    float a, ga[3], u[3];
    uint32_t oct, meta = P->meta, cnt = POLYCC_META_COUNT(meta);
    float px = p[0], py = p[1], pz = p[2];
    if (polycc_culled((float)P->r_out * q_out, (float)P->inv_gamma * POLYCC_INV_GAMMA_UNIT,
                      polycc_dist2u(P, q, px, py, pz, u), s->Tp)) {
        return; /* max_l g_kl >= gamma (|u| - r_out) > T */
    }
    /* octant of u from the sign bits (-0.0 counts as negative; only picks the lead plane) */
    oct = (polycc_bits(u[0]) >> 31) | ((polycc_bits(u[1]) >> 30) & 2u) | ((polycc_bits(u[2]) >> 29) & 4u);
    if (!polycc_softmax_poly(base, cnt, POLYCC_META_LEAD(meta, oct), nrm, q, px, py, pz, kappa, neg_cut, s->T, &a,
                             ga)) {
        return;
    }
    if (s->nev == 0u) {
        s->cur = a;
        s->S2 = 1.0f;
        s->G[0] = ga[0];
        s->G[1] = ga[1];
        s->G[2] = ga[2];
    } else if (a < s->cur) {
        float r = polycc_exp_le88(kappa * (a - s->cur));
        s->S2 = r * s->S2 + 1.0f;
        s->G[0] = r * s->G[0] + ga[0];
        s->G[1] = r * s->G[1] + ga[1];
        s->G[2] = r * s->G[2] + ga[2];
        s->cur = a;
    } else {
        float x = kappa * (s->cur - a);
        if (x > -POLYCC_NEGLIGIBLE_NATS) {
            float e = polycc_exp_le88(x);
            s->S2 = s->S2 + e;
            s->G[0] = s->G[0] + e * ga[0];
            s->G[1] = s->G[1] + e * ga[1];
            s->G[2] = s->G[2] + e * ga[2];
        }
    }
    ++s->nev;
    s->T = (s->cur < s->a_ref ? s->cur : s->a_ref) + s->slack;
    s->Tp = s->T > 0.0f ? s->T : 0.0f;
}

/* Pass 1 step: a_ref <- |p - c| - r_in if that is lower (sqrt only then). */
POLYCC_INLINE float polycc_aref_step(const polycc_poly_t *P, float q, float px, float py, float pz, float a_ref)
{
    float u[3];
    float d2 = polycc_dist2u(P, q, px, py, pz, u);
    float r_in = (float)P->r_in * q;
    float t = a_ref + r_in;
    if (t > 0.0f && d2 < t * t) {
        a_ref = sqrtf(d2) - r_in;
    }
    return a_ref;
}

uint32_t polycc_barrier(const polycc_scene_t *scene, const polycc_params_t *params, const float p[3], float *psi,
                        float grad[3])
{
    float px, py, pz, kappa, invk, neg_cut, marg, q, q_out, psi0;
    uint32_t j, m = 0u;
    const polycc_normal_t *nrm;
    const polycc_index_t *ix;
    const uint16_t *list = NULL;
    polycc_smin_t s;
    *psi = 0.0f;
    grad[0] = 0.0f;
    grad[1] = 0.0f;
    grad[2] = 0.0f;
    if (!polycc_scene_ok(scene) || !polycc_params_ok(params) || !polycc_coord_ok(p[0]) || !polycc_coord_ok(p[1]) ||
        !polycc_coord_ok(p[2])) {
        return POLYCC_FLAG_INVALID;
    }
    px = p[0];
    py = p[1];
    pz = p[2];
    q = scene->quantum;
    q_out = q * POLYCC_R_OUT_QUANTA; /* exact: powers of two */
    nrm = scene->normals;
    kappa = params->kappa;
    invk = 1.0f / kappa;
    neg_cut = -POLYCC_NEGLIGIBLE_NATS * invk;
    s.slack = (POLYCC_NEGLIGIBLE_NATS + scene->log_lmax) * invk;
    ix = scene->index;
    if (ix != NULL) {
        /* The cell of p (section 9); outside the grid box B the list stays empty (psi0 = D). */
        float tx = (px - ix->ox) * ix->inv_cell, ty = (py - ix->oy) * ix->inv_cell, tz = (pz - ix->oz) * ix->inv_cell;
        if (tx >= 0.0f && tx < (float)ix->nx && ty >= 0.0f && ty < (float)ix->ny && tz >= 0.0f &&
            tz < (float)ix->nz) {
            uint32_t c = (uint32_t)tx + (uint32_t)ix->nx * ((uint32_t)ty + (uint32_t)ix->ny * (uint32_t)tz);
            uint32_t id = ix->cell_list[c];
            while (id >= ix->n_lists) { /* octree descent: t doubled exactly, octant from the parities */
                tx = tx * 2.0f;
                ty = ty * 2.0f;
                tz = tz * 2.0f;
                id = ix->children[8u * (id - ix->n_lists) + (((uint32_t)tx & 1u) | (((uint32_t)ty & 1u) << 1) |
                                                            (((uint32_t)tz & 1u) << 2))];
            }
            list = ix->entries + ix->list_start[id];
            m = (uint32_t)ix->list_start[id + 1u] - (uint32_t)ix->list_start[id];
        }
    }

    /* Pass 1: a_ref = min_k (|p - c_k| - r_in_k) >= min_k max_l g_kl over the candidates (the clusters
     * that can lower it, or the cell's list); any a_ref >= that minimum is safe. */
    s.a_ref = 3.0e38f;
    if (ix != NULL) {
        for (j = 0; j < m; ++j) {
            s.a_ref = polycc_aref_step(&scene->polys[list[j]], q, px, py, pz, s.a_ref);
        }
    } else {
        for (j = 0; j < scene->n_clusters; ++j) {
            const polycc_cluster_t *C = &scene->clusters[j];
            const polycc_poly_t *P = &scene->polys[C->first];
            const polycc_poly_t *Pend = P + C->count;
            float t = s.a_ref + C->r_in;
            if (!(t > 0.0f && polycc_dist2c(C, px, py, pz) < t * t)) {
                continue;
            }
            for (; P < Pend; ++P) {
                s.a_ref = polycc_aref_step(P, q, px, py, pz, s.a_ref);
            }
        }
    }

    /* Pass 2: cull clusters and polytopes, Boltzmann soft-max per polytope, online soft-min.
     * T = min(a_ref, cur) + slack is the culling threshold (recomputed when cur drops). */
    s.T = s.a_ref + s.slack;
    s.Tp = s.T > 0.0f ? s.T : 0.0f;
    s.cur = 0.0f;
    s.S2 = 0.0f;
    s.G[0] = 0.0f;
    s.G[1] = 0.0f;
    s.G[2] = 0.0f;
    s.nev = 0u;
    if (ix != NULL) {
        for (j = 0; j < m; ++j) {
            uint32_t k = list[j];
            polycc_visit(&scene->polys[k], &scene->planes[ix->poly_first[k]], nrm, q, q_out, p, kappa, neg_cut, &s);
        }
    } else {
        for (j = 0; j < scene->n_clusters; ++j) {
            const polycc_cluster_t *C = &scene->clusters[j];
            const polycc_poly_t *P = &scene->polys[C->first];
            const polycc_poly_t *Pend = P + C->count;
            const polycc_plane_t *pl = &scene->planes[C->first_plane];
            if (polycc_culled(C->r_out, C->inv_gamma, polycc_dist2c(C, px, py, pz), s.Tp)) {
                continue;
            }
            for (; P < Pend; ++P) {
                const polycc_plane_t *base = pl;
                pl += POLYCC_META_COUNT(P->meta);
                polycc_visit(P, base, nrm, q, q_out, p, kappa, neg_cut, &s);
            }
        }
    }

    marg = POLYCC_MARGIN_REL *
           ((((fabsf(px) + fabsf(py)) + fabsf(pz)) + scene->coord_bound) + params->radius + 32.0f * invk);
    psi0 = POLYCC_PSI_EMPTY;
    if (s.nev != 0u) {
        float invS2 = 1.0f / s.S2;
        psi0 = s.cur - polycc_log(s.S2) * invk;
        grad[0] = s.G[0] * invS2;
        grad[1] = s.G[1] * invS2;
        grad[2] = s.G[2] * invS2;
    }
    if (ix != NULL && !(psi0 < ix->cap)) { /* clearance cap: psi0' = min(psi0, D), no gradient */
        psi0 = ix->cap;
        grad[0] = 0.0f;
        grad[1] = 0.0f;
        grad[2] = 0.0f;
    }
    *psi = psi0 - (params->radius + marg);
    if (!polycc_finite(*psi) || !polycc_finite(grad[0]) || !polycc_finite(grad[1]) || !polycc_finite(grad[2])) {
        *psi = 0.0f;
        grad[0] = 0.0f;
        grad[1] = 0.0f;
        grad[2] = 0.0f;
        return POLYCC_FLAG_INVALID;
    }
    return 0u;
}

/* Scales v in place to norm <= vmax; returns POLYCC_FLAG_SATURATED if it did (also used by the shield
 * and the swarm step). */
uint32_t polycc_saturate(float v[3], float vmax)
{
    float n2 = (v[0] * v[0] + v[1] * v[1]) + v[2] * v[2];
    float s;
    if (!(n2 > vmax * vmax)) {
        return 0u;
    }
    s = vmax / sqrtf(n2);
    v[0] = v[0] * s;
    v[1] = v[1] * s;
    v[2] = v[2] * s;
    return POLYCC_FLAG_SATURATED;
}

static void polycc_zero_out(polycc_out_t *out)
{
    int i;
    for (i = 0; i < 3; ++i) {
        out->u[i] = 0.0f;
        out->u_nom[i] = 0.0f;
        out->grad[i] = 0.0f;
    }
    out->psi = 0.0f;
    out->flags = 0u;
}

uint32_t polycc_step(const polycc_scene_t *scene, const polycc_params_t *params, const float x[3],
                     const float goal[3], polycc_out_t *out)
{
    uint32_t flags;
    float h, dot, viol;
    int i;
    polycc_zero_out(out);
    for (i = 0; i < 3; ++i) {
        if (!polycc_coord_ok(goal[i])) {
            out->flags = POLYCC_FLAG_INVALID;
            return out->flags;
        }
    }
    flags = polycc_barrier(scene, params, x, &out->psi, out->grad);
    if (flags & POLYCC_FLAG_INVALID) {
        out->flags = flags;
        return flags;
    }
    /* CLF: the QP solution is u = -(c V / |e|^2) e = -(c/2) e (and 0 at the goal). */
    h = -0.5f * params->c_clf;
    for (i = 0; i < 3; ++i) {
        out->u_nom[i] = h * (x[i] - goal[i]);
    }
    flags |= polycc_saturate(out->u_nom, params->v_max);

    /* CBF filter: half-space projection of u_nom onto { u : grad psi . u >= -beta psi }. */
    dot = (out->grad[0] * out->u_nom[0] + out->grad[1] * out->u_nom[1]) + out->grad[2] * out->u_nom[2];
    viol = dot + params->beta * out->psi;
    for (i = 0; i < 3; ++i) {
        out->u[i] = out->u_nom[i];
    }
    if (viol < 0.0f) {
        float g2 = (out->grad[0] * out->grad[0] + out->grad[1] * out->grad[1]) + out->grad[2] * out->grad[2];
        float lam;
        if (!(g2 >= POLYCC_GRAD2_MIN)) {
            polycc_zero_out(out);
            out->flags = POLYCC_FLAG_INVALID | POLYCC_FLAG_DEGENERATE;
            return out->flags;
        }
        lam = -viol / g2;
        for (i = 0; i < 3; ++i) {
            out->u[i] = out->u[i] + lam * out->grad[i];
        }
        flags |= POLYCC_FLAG_ACTIVE;
        flags |= polycc_saturate(out->u, params->v_max);
    }
    if (out->psi < 0.0f) {
        flags |= POLYCC_FLAG_INSIDE;
    }
    for (i = 0; i < 3; ++i) {
        if (!polycc_finite(out->u[i]) || !polycc_finite(out->u_nom[i])) {
            polycc_zero_out(out);
            out->flags = POLYCC_FLAG_INVALID;
            return out->flags;
        }
    }
    out->flags = flags;
    return flags;
}
