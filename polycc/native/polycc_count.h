/* Occupied voxels entirely inside a convex polytope, within an index box (host only, float64).
 *
 * The numpy reference is polycc.cover.merge.VoxelBoxQuery.count_inside (same predicate, same
 * column arithmetic); polycc/native/__init__.py wraps this. Voxel v occupies [v, v + 1)^3 in
 * lattice units; the polytope is {q : A q + b <= 0}, rows A[3 f .. 3 f + 2], b[f]. */
#ifndef POLYCC_COUNT_H
#define POLYCC_COUNT_H

#include <stdint.h>

/* The occupied voxels are given either dense (dense: shape[0] x shape[1] x shape[2] bytes, C order;
 * sat: the summed-volume table, (shape + 1) cells, sat[x, y, z] = occupied voxels below (x, y, z)) or,
 * with dense == NULL, as keys: for each axis a, nkeys sorted int64 keys at keys[a * nkeys]
 * ((u * shape[v] + v) * (shape[a] + 1) + t, (u, v) the other two axes in order, t along a).
 * lo, hi: the inclusive index box (clipped to the grid here). Boxes of at most direct_cells cells
 * of a dense grid are tested voxel by voxel, others column by column along their longest axis. */
int64_t polycc_count_inside(const uint8_t *dense, const int32_t *sat, const int64_t *keys, int64_t nkeys,
                            const int64_t *shape, const double *A, const double *b, int64_t F, const int64_t *lo,
                            const int64_t *hi, double tol, int64_t direct_cells);

#endif
