/* Host-side planning (polycc_plan.c): grid A* and the certified field. Not firmware. */
#ifndef POLYCC_PLAN_H
#define POLYCC_PLAN_H

#include <stdint.h>

/* free_cells: n = nx*ny*nz bytes, nonzero = traversable; g: n + 1 doubles set to +inf (out: cost
 * from the sources, g[n] = cost to the goal); parent: n entries (out, -1 at a source); dst sorted
 * ascending. info (out): [0] target cell the goal was reached through (-1: none), [1] cells
 * expanded, [2] heap capacity. Returns 0 (path found), 1 (no path), -1 (out of memory). */
int polycc_astar(const uint8_t *free_cells, int32_t nx, int32_t ny, int32_t nz, double spacing,
                 const int64_t *src, const double *src_cost, int32_t n_src,
                 const int64_t *dst, const double *dst_cost, int32_t n_dst,
                 int32_t gx, int32_t gy, int32_t gz, double shift, double weight,
                 double *g, int64_t *parent, int64_t *info);

/* Soft-min sums of the certified field (polycc/plan/grid.py): planes (P, 4) rows [nx, ny, nz, d];
 * blocks (K, 6) cell ranges [i0, i1, j0, j1, k0, k1); vmin, ssum (nx, ny, nz) updated in place. */
void polycc_lower_field(const double *planes, const int64_t *first, const int64_t *count, const double *c,
                        const int64_t *blocks, const double *centre, const double *reach, int32_t n_polys,
                        const double *lo, double spacing, int32_t nx, int32_t ny, int32_t nz, double kappa,
                        double e, double *vmin, double *ssum);

#endif
