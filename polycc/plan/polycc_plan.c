/* Host-side planning (polycc/plan/native.py; not firmware): A* on a 26-connected voxel grid and the
 * soft-min sums of the certified field.
 *
 * Cells are indexed (i*ny + j)*nz + k (C order of an (nx, ny, nz) array). A move to one of the 26
 * neighbours costs spacing * {1, sqrt 2, sqrt 3}. Several source cells (each with a start cost)
 * and several target cells (each with a cost to the real goal) are allowed: the search ends when
 * the virtual goal (node n) is popped, reached from a target at its g plus its goal cost.
 *
 * Heuristic: max(0, octile(c, goal_cell) * spacing - shift), the exact 26-connected grid distance
 * to the goal's cell minus shift >= max_t (octile(t, goal_cell) * spacing - goal_cost_t); octile is
 * a norm, so this is consistent and admissible for the virtual goal (the search is optimal on the
 * grid). Ties in f go to the larger g (deeper nodes first).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "polycc_plan.h"

typedef struct {
    double f;
    double g;
    int64_t node;
} entry_t;

typedef struct {
    entry_t *a;
    size_t n, cap;
} heap_t;

static int before(const entry_t *x, const entry_t *y)
{
    return x->f < y->f || (x->f == y->f && x->g > y->g);
}

static int heap_push(heap_t *h, double f, double g, int64_t node)
{
    size_t i;
    if (h->n == h->cap) {
        size_t cap = h->cap ? 2 * h->cap : 4096;
        entry_t *a = (entry_t *)realloc(h->a, cap * sizeof(entry_t));
        if (a == NULL) {
            return -1;
        }
        h->a = a;
        h->cap = cap;
    }
    i = h->n++;
    h->a[i].f = f;
    h->a[i].g = g;
    h->a[i].node = node;
    while (i > 0) {
        size_t p = (i - 1) / 2;
        entry_t t;
        if (!before(&h->a[i], &h->a[p])) {
            break;
        }
        t = h->a[i];
        h->a[i] = h->a[p];
        h->a[p] = t;
        i = p;
    }
    return 0;
}

static entry_t heap_pop(heap_t *h)
{
    entry_t top = h->a[0];
    size_t i = 0;
    h->a[0] = h->a[--h->n];
    for (;;) {
        size_t l = 2 * i + 1, r = l + 1, m = i;
        entry_t t;
        if (l < h->n && before(&h->a[l], &h->a[m])) {
            m = l;
        }
        if (r < h->n && before(&h->a[r], &h->a[m])) {
            m = r;
        }
        if (m == i) {
            break;
        }
        t = h->a[i];
        h->a[i] = h->a[m];
        h->a[m] = t;
        i = m;
    }
    return top;
}

static double octile(int64_t dx, int64_t dy, int64_t dz)
{
    int64_t a = dx < 0 ? -dx : dx, b = dy < 0 ? -dy : dy, c = dz < 0 ? -dz : dz, t;
    if (a < b) { t = a; a = b; b = t; }
    if (b < c) { t = b; b = c; c = t; }
    if (a < b) { t = a; a = b; b = t; }
    /* a >= b >= c: c body diagonals, b - c face diagonals, a - b axis moves */
    return 1.7320508075688772 * (double)c + 1.4142135623730951 * (double)(b - c) + (double)(a - b);
}

#define CLOSED 1u
#define TARGET 2u

static int find_target(const int64_t *dst, int n_dst, int64_t node)
{
    int lo = 0, hi = n_dst - 1;
    while (lo <= hi) {
        int mid = lo + (hi - lo) / 2;
        if (dst[mid] == node) {
            return mid;
        }
        if (dst[mid] < node) {
            lo = mid + 1;
        } else {
            hi = mid - 1;
        }
    }
    return -1;
}

int polycc_astar(const uint8_t *free_cells, int32_t nx, int32_t ny, int32_t nz, double spacing,
                 const int64_t *src, const double *src_cost, int32_t n_src,
                 const int64_t *dst, const double *dst_cost, int32_t n_dst,
                 int32_t gx, int32_t gy, int32_t gz, double shift, double weight,
                 double *g, int64_t *parent, int64_t *info)
{
    const int64_t n = (int64_t)nx * ny * nz;
    const int64_t syz = (int64_t)ny * nz;
    uint8_t *state;
    heap_t heap = {NULL, 0, 0};
    int64_t expanded = 0, via = -1;
    double best = INFINITY;
    int d, rc = 1;
    int64_t off[26];
    int dxs[26], dys[26], dzs[26];
    double w[26];
    int m = 0;
    int dx, dy, dz;
    for (dx = -1; dx <= 1; ++dx) {
        for (dy = -1; dy <= 1; ++dy) {
            for (dz = -1; dz <= 1; ++dz) {
                if (dx == 0 && dy == 0 && dz == 0) {
                    continue;
                }
                dxs[m] = dx;
                dys[m] = dy;
                dzs[m] = dz;
                off[m] = dx * syz + dy * (int64_t)nz + dz;
                w[m] = spacing * sqrt((double)(dx * dx + dy * dy + dz * dz));
                ++m;
            }
        }
    }
    state = (uint8_t *)calloc((size_t)n, 1);
    if (state == NULL) {
        return -1;
    }
    for (d = 0; d < n_dst; ++d) {
        state[dst[d]] |= TARGET;
    }
    for (d = 0; d < n_src; ++d) {
        int64_t s = src[d];
        if (src_cost[d] < g[s]) {
            int64_t i = s / syz, j = (s / nz) % ny, k = s % nz;
            double h = octile(i - gx, j - gy, k - gz) * spacing - shift;
            g[s] = src_cost[d];
            parent[s] = -1;
            if (heap_push(&heap, src_cost[d] + weight * (h > 0.0 ? h : 0.0), src_cost[d], s) != 0) {
                rc = -1;
                goto done;
            }
        }
    }
    while (heap.n > 0) {
        entry_t e = heap_pop(&heap);
        int64_t c = e.node, i, j, k;
        if (c == n) { /* the virtual goal */
            rc = 0;
            break;
        }
        if ((state[c] & CLOSED) || e.g > g[c]) {
            continue;
        }
        state[c] |= CLOSED;
        ++expanded;
        if (state[c] & TARGET) {
            int t = find_target(dst, n_dst, c);
            double gg = g[c] + dst_cost[t];
            if (gg < best) {
                best = gg;
                via = c;
                if (heap_push(&heap, gg, gg, n) != 0) {
                    rc = -1;
                    goto done;
                }
            }
        }
        i = c / syz;
        j = (c / nz) % ny;
        k = c % nz;
        for (d = 0; d < 26; ++d) {
            int64_t ii = i + dxs[d], jj = j + dys[d], kk = k + dzs[d], q;
            double gq, h;
            if (ii < 0 || ii >= nx || jj < 0 || jj >= ny || kk < 0 || kk >= nz) {
                continue;
            }
            q = c + off[d];
            if (!free_cells[q] || (state[q] & CLOSED)) {
                continue;
            }
            gq = g[c] + w[d];
            if (gq < g[q]) {
                g[q] = gq;
                parent[q] = c;
                h = octile(ii - gx, jj - gy, kk - gz) * spacing - shift;
                if (heap_push(&heap, gq + weight * (h > 0.0 ? h : 0.0), gq, q) != 0) {
                    rc = -1;
                    goto done;
                }
            }
        }
    }
done:
    info[0] = via;
    info[1] = expanded;
    info[2] = (int64_t)heap.cap;
    if (rc == 0) {
        g[n] = best; /* caller passes g with n + 1 entries */
    }
    free(heap.a);
    free(state);
    return rc;
}

/* The soft-min sums of polycc/plan/grid.py (lower_field): for every polytope k and every cell
 * centre p of its block [i0, i1) x [j0, j1) x [k0, k1) with |p - centre_k| < reach_k and
 * phi = max_l (n_l . p - d_l) < e, fold v = phi - c_k into (vmin, ssum):
 * vmin' = min(vmin, v), ssum' = ssum exp(-kappa (vmin - vmin')) + exp(-kappa (v - vmin')). */
void polycc_lower_field(const double *planes, const int64_t *first, const int64_t *count, const double *c,
                        const int64_t *blocks, const double *centre, const double *reach, int32_t n_polys,
                        const double *lo, double spacing, int32_t nx, int32_t ny, int32_t nz, double kappa,
                        double e, double *vmin, double *ssum)
{
    int32_t k;
    (void)nx;
    for (k = 0; k < n_polys; ++k) {
        const double *h = planes + 4 * first[k];
        const int64_t L = count[k], *b = blocks + 6 * k;
        const double cx = centre[3 * k], cy = centre[3 * k + 1], cz = centre[3 * k + 2];
        const double r2 = reach[k] * reach[k];
        int64_t i, j, q;
        for (i = b[0]; i < b[1]; ++i) {
            const double x = lo[0] + ((double)i + 0.5) * spacing, dx = x - cx;
            for (j = b[2]; j < b[3]; ++j) {
                const double y = lo[1] + ((double)j + 0.5) * spacing, dy = y - cy;
                double *vm = vmin + ((int64_t)i * ny + j) * nz, *ss = ssum + ((int64_t)i * ny + j) * nz;
                for (q = b[4]; q < b[5]; ++q) {
                    const double z = lo[2] + ((double)q + 0.5) * spacing, dz = z - cz;
                    double phi = -INFINITY, v, m;
                    int64_t l;
                    if (dx * dx + dy * dy + dz * dz >= r2) {
                        continue;
                    }
                    for (l = 0; l < L; ++l) {
                        const double g = h[4 * l] * x + h[4 * l + 1] * y + h[4 * l + 2] * z - h[4 * l + 3];
                        if (g > phi) {
                            phi = g;
                            if (phi >= e) {
                                break;
                            }
                        }
                    }
                    if (!(phi < e)) {
                        continue;
                    }
                    v = phi - c[k];
                    m = vm[q];
                    if (v < m) {
                        ss[q] = ss[q] * exp(-kappa * (m - v)) + 1.0;
                        vm[q] = v;
                    } else {
                        ss[q] += exp(-kappa * (v - m));
                    }
                }
            }
        }
    }
}
