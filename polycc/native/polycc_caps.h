/* Drop volumes of a small convex polytope, every plane at once (host only, float64).
 *
 * P = {p : n_l . p <= d_l}, rows h[4 l .. 4 l + 3] = (nx, ny, nz, d), world frame, metres.
 * The numpy reference is polycc.geometry.halfplanes.drop_volumes; polycc/native/__init__.py wraps this. */
#ifndef POLYCC_CAPS_H
#define POLYCC_CAPS_H

#include <stdint.h>

#define POLYCC_CAPS_MAX_PLANES 128

/* vol[j]: volume (m^3) that dropping plane j adds to P (0 if it touches no vertex of P);
 * state[j]: 1 if the other planes' normals are bounded with margin min_gamma, 0 if not,
 * -1 if too close to call (the caller decides with qhull). Returns 0, or -1 if m is out of
 * range, a normal is zero or memory ran out (vol and state are then undefined). */
int polycc_cap_volumes(const double *h, int m, double min_gamma, double *vol, int8_t *state);

/* state[j] of polycc_cap_volumes alone, from the normals n[3 l .. 3 l + 2] (any length > 0). */
int polycc_bounded_without(const double *n, int m, double min_gamma, int8_t *state);

#endif
