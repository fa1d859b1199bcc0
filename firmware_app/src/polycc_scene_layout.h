/*
 * polycc_scene_layout.h -- the scene data layout read by the on-board barrier kernel.
 *
 * The code generator (polycc codegen) instantiates this layout as sized `static const`
 * arrays plus one root `polycc_scene_t`; `polycc/scene_layout.py` builds and decodes
 * exactly these bytes.  Portable C99, no firmware headers.
 *
 * Format 2 (POLYCC_SCENE_FORMAT == 2): float32, little-endian, 4-byte aligned.
 * (Format 1 was a draft without clusters and lead planes; its headers no longer compile.)
 *
 *   planes[n_planes]   polycc_plane_t, 16 bytes each: {nx, ny, nz, d}
 *                      The half-plane value is g(p) = nx*px + ny*py + nz*pz - d.
 *                      Polytope k is the set { p : g_l(p) <= 0 for every plane l of k }.
 *                      Normals are outward and unit length in float64 up to float32
 *                      rounding (every |component| <= 1).  The certified inequality is
 *                      stated for the float32 values stored here, read as exact numbers.
 *                      The planes of one polytope are contiguous.
 *
 *   polys[n_polys]     polycc_poly_t, 36 bytes each:
 *                      first, count  range of this polytope's planes in planes[] (1 <= count <= 256)
 *                      cx, cy, cz    culling centre c_k: a point strictly inside the polytope
 *                      r_out         outer culling radius R_k, rounded up, such that for all p
 *                                        max_l g_kl(p) >= gamma_k * (|p - c_k| - R_k)
 *                      inv_gamma     1/gamma_k, rounded up, where
 *                                        gamma_k = min_{|u|=1} max_l n_kl . u  (> 0 if bounded)
 *                                    R_k = max_l (d_kl - n_kl . c_k) / gamma_k is the radius of
 *                                    the smallest ball about c_k that this bound certifies; it is
 *                                    >= the circumradius about c_k (equal for a cube).
 *                      r_in          inner radius, rounded down: r_in = min_l (d_kl - n_kl . c_k),
 *                                    so that max_l g_kl(p) <= |p - c_k| - r_in for all p.
 *                                    Only used to pick the culling threshold (speed, not safety).
 *
 *   clusters[n_clusters]  polycc_cluster_t (same 36-byte record, lead unused), a one-level bounding
 *                      hierarchy over the polytopes: cluster j holds polys[first .. first+count-1]
 *                      (polytopes are stored grouped by cluster, clusters cover polys[] in order)
 *                      cx, cy, cz    cluster centre C
 *                      r_out         max_k (|c_k - C| + r_out_k), rounded up
 *                      inv_gamma     max_k inv_gamma_k
 *                      r_in          max_k (|c_k - C| + r_in_k), rounded up ("reach": no polytope of
 *                                    the cluster has |p - c_k| - r_in_k < |p - C| - r_in)
 *                      so that gamma_C (|p - C| - r_out) <= max_l g_kl(p) for every k of the cluster
 *                      whenever |p - C| >= r_out.
 *
 *   scene              polycc_scene_t: format tag, counts, two scene constants, array pointers:
 *                      coord_bound  >= max(max_l |d_l|, max_k (|c_k|_1 + r_out_k))
 *                                   (scale of the rounding margin, see docs/barrier.md)
 *                      log_lmax     >= ln(max_k count_k) (soft-max slack used by the culling test)
 *
 * Flash cost: 16 bytes per half-plane + 36 bytes per polytope + 36 bytes per cluster + 36 bytes
 * of root struct.  64 KB holds 150 polytopes (13 clusters) with about 3720 half-planes.  Half-planes are stored as
 * float32 because the kernel's inner loop is load-bound on the Cortex-M4 (4 VLDR and 6
 * FPU operations per half-plane); an int16 variant would need 4 extra conversions per
 * half-plane.  A future quantized format must bump POLYCC_SCENE_FORMAT.
 *
 * The app must refuse a scene whose `format` differs from POLYCC_SCENE_FORMAT (the kernel
 * returns POLYCC_FLAG_INVALID for it).  Compile-time check for generated headers:
 *     #if POLYCC_SCENE_FORMAT != 2
 *     #error "polytopes.h was generated for scene format 2"
 *     #endif
 */
#ifndef POLYCC_SCENE_LAYOUT_H
#define POLYCC_SCENE_LAYOUT_H

#include <stdint.h>

#define POLYCC_SCENE_FORMAT 2u

/* Byte sizes of the records, checked by polycc/scene_layout.py and the tests. */
#define POLYCC_PLANE_BYTES 16u
#define POLYCC_POLY_BYTES 36u
#define POLYCC_CLUSTER_BYTES 36u

/* Largest number of half-planes a scene may hold (uint16_t plane indices) and per polytope
 * (uint8_t lead indices). */
#define POLYCC_MAX_PLANES 65535u
#define POLYCC_MAX_POLY_PLANES 256u

typedef struct polycc_plane {
    float nx, ny, nz; /* outward unit normal */
    float d;          /* offset: g(p) = n . p - d */
} polycc_plane_t;

typedef struct polycc_poly {
    uint16_t first;  /* index of the first half-plane in planes[] */
    uint16_t count;  /* number of half-planes, >= 1 */
    float cx, cy, cz; /* culling centre (interior point) */
    float r_out;     /* outer culling radius, rounded up */
    float inv_gamma; /* 1 / gamma, rounded up (>= 1) */
    float r_in;      /* inner radius, rounded down */
    uint8_t lead[8]; /* per octant o of p - c (bit0: x < 0, bit1: y < 0, bit2: z < 0): index of
                        the plane to evaluate first, argmax_l n_l . s_o (s_o = (+-1, +-1, +-1));
                        any value < count is correct, this one makes far polytopes cheap */
} polycc_poly_t;

/* A cluster record has the polytope record's layout; first/count index polys[]. */
typedef polycc_poly_t polycc_cluster_t;

typedef struct polycc_scene {
    uint32_t format;      /* POLYCC_SCENE_FORMAT */
    uint32_t n_clusters;  /* number of clusters (>= 1 if n_polys > 0) */
    uint32_t n_polys;     /* number of polytopes */
    uint32_t n_planes;    /* number of half-planes */
    float coord_bound;    /* rounding-margin scale, see above */
    float log_lmax;       /* >= ln(max half-planes per polytope) */
    const polycc_cluster_t *clusters;
    const polycc_poly_t *polys;
    const polycc_plane_t *planes;
} polycc_scene_t;

#endif /* POLYCC_SCENE_LAYOUT_H */
