/*
 * polycc_scene_layout.h -- the scene data layout read by the on-board barrier kernel.
 *
 * The code generator (polycc codegen) instantiates this layout as sized `static const`
 * arrays plus one root `polycc_scene_t`; `polycc/onboard/layout.py` builds and decodes
 * exactly these bytes.  Portable C99, no firmware headers.
 *
 * Format 3 (POLYCC_SCENE_FORMAT == 3): quantized, little-endian, 4-byte aligned.
 * (Format 2 stored float32 half-planes, 16 B each, and 36-byte polytope records; format 1 was
 * a draft.  Their headers no longer compile against this kernel.)
 *
 * Every stored number decodes EXACTLY to a float32 (an int16/uint16 times a power of two, or a
 * float32), and every certified statement of the kernel (docs/barrier.md) is made for the
 * decoded values, read as exact reals.  The generator rounds outward: each decoded half-space
 * contains the exact polytope (d >= max over its vertices of n . v), see "Quantization" in
 * docs/barrier.md.  Notation: q = scene->quantum (a power of two, metres).
 *
 *   normals[n_normals]  polycc_normal_t, 12 bytes: {nx, ny, nz} float32, shared by all planes.
 *                       |n| <= 1 as exact numbers (unit up to one float32 rounding toward 0).
 *
 *   planes[n_planes]    polycc_plane_t, 4 bytes: {normal, d}
 *                       normal  index into normals[]
 *                       d       offset in quanta: the plane is g(p) = n . p - d * q
 *                       Polytope k is the set { p : g_l(p) <= 0 for every plane l of k }.
 *                       The planes of one polytope are contiguous, polytopes in polys[] order;
 *                       its lead planes (below) come first.
 *
 *   polys[n_polys]      polycc_poly_t, 16 bytes:
 *                       c[3]       culling centre c_k = c * q, a point strictly inside
 *                       r_out      outer culling radius R_k = r_out * 16 q, rounded up, such that
 *                                      max_l g_kl(p) >= gamma_k * (|p - c_k| - R_k)  for all p
 *                       r_in       inner radius r_in * q, rounded down: max_l g_kl(p) <= |p - c_k| - r_in
 *                                  (picks the culling threshold only: speed, not safety)
 *                       inv_gamma  1/gamma_k = inv_gamma * 2^-8, rounded up,
 *                                      gamma_k = min_{|u|=1} max_l n_kl . u  (> 0: bounded)
 *                       meta       bits 0..7: count - 1 (1 <= count <= 256 half-planes);
 *                                  bits 8+3o .. 10+3o: lead plane of octant o of p - c
 *                                  (bit0: x < 0, bit1: y < 0, bit2: z < 0), an index < 8:
 *                                  argmax_l n_l . s_o, s_o = (+-1, +-1, +-1).  Any index < count
 *                                  would be correct; this one makes far polytopes cheap.
 *                       The first plane of polytope k is the cluster's first_plane plus the
 *                       counts of the polytopes before k in its cluster (no per-polytope index).
 *
 *   clusters[n_clusters] polycc_cluster_t, 32 bytes (float32 bounds, few records):
 *                       first, count  range of polytopes in polys[] (clusters cover polys[] in order)
 *                       first_plane   index in planes[] of the first plane of polys[first]
 *                       cx, cy, cz    cluster centre C
 *                       r_out         max_k (|c_k - C| + R_k), rounded up
 *                       inv_gamma     max_k 1/gamma_k
 *                       r_in          max_k (|c_k - C| + r_in_k), rounded up
 *                       so that gamma_C (|p - C| - r_out) <= max_l g_kl(p) for every k of the cluster.
 *
 *   scene               polycc_scene_t: format tag, counts, three scene constants, array pointers:
 *                       quantum      q: a power of two in [2^-20, 2^4] (the kernel checks)
 *                       coord_bound  >= max(max_l |d_l q|, max_k (|c_k|_1 + R_k))
 *                       log_lmax     >= ln(max_k count_k)
 *
 * Flash bytes (exact, 32-bit target; polycc.scene_layout.layout_bytes):
 *     52 + 4 * n_planes + 16 * n_polys + 32 * n_clusters + 12 * n_normals
 *     (+ with an index: 56 + 2 * (n_cells + 8 n_inner + n_lists + 1 + n_entries + n_polys), each array
 *      padded to 4 bytes)
 * e.g. 10 half-planes per polytope, 13 polytopes per cluster, 400 distinct normals per 8000
 * planes: 4 + 1.6 + 0.25 + 0.6 = 6.4 bytes per half-plane.  Distinct normals cost 12 B each:
 * covers whose normals repeat (lattice normals of voxel hulls, k-DOPs, or a table capped by
 * pack_scene(max_normals=T)) meet 8 B per half-plane; unique normals cost 16 + 16/H B per
 * half-plane (format 2: 16 + 36/H).
 *
 * Why this and not int16 normals (8 B per plane): polytope records would still cost
 * 16-36 B per 6-20 planes, so 8 B per plane plus records misses 8 B on average; and the
 * shared table costs no decoding in the inner loop (an index load instead of 3 VLDR, plus one
 * int->float conversion and one exact multiply for d).  Measured in bench/bench_kernel.py.
 *
 * The app must refuse a scene whose `format` differs from POLYCC_SCENE_FORMAT (the kernel
 * returns POLYCC_FLAG_INVALID for it).  Compile-time check for generated headers:
 *     #if POLYCC_SCENE_FORMAT != 3
 *     #error "polytopes.h was generated for scene format 3"
 *     #endif
 */
#ifndef POLYCC_SCENE_LAYOUT_H
#define POLYCC_SCENE_LAYOUT_H

#include <stdint.h>

#define POLYCC_SCENE_FORMAT 3u

/* Byte sizes of the records, checked by polycc/onboard/layout.py and the tests.  The root struct
 * is POLYCC_ROOT_BYTES on a 32-bit target (8 words + 5 pointers). */
#define POLYCC_NORMAL_BYTES 12u
#define POLYCC_PLANE_BYTES 4u
#define POLYCC_POLY_BYTES 16u
#define POLYCC_CLUSTER_BYTES 32u
#define POLYCC_ROOT_BYTES 52u
#define POLYCC_INDEX_BYTES 56u

/* Limits: half-planes per scene, polytopes (uint16_t cluster index), half-planes per polytope (8-bit count - 1), distinct normals (uint16_t
 * index), lead planes (3-bit index). */
#define POLYCC_MAX_PLANES 65535u
#define POLYCC_MAX_POLYS 65535u
#define POLYCC_MAX_POLY_PLANES 256u
#define POLYCC_MAX_NORMALS 65536u
#define POLYCC_LEAD_PLANES 8u
/* Polytope r_out is stored in units of 16 quanta (range 2^20 q; sliver polytopes have large R). */
#define POLYCC_R_OUT_QUANTA 16.0f
/* inv_gamma = stored value * POLYCC_INV_GAMMA_UNIT (exact). */
#define POLYCC_INV_GAMMA_UNIT 0x1p-8f

/* meta field of polycc_poly_t */
#define POLYCC_META(count, leads24) ((uint32_t)((count) - 1u) | ((uint32_t)(leads24) << 8))
#define POLYCC_META_COUNT(meta) (((meta) & 0xffu) + 1u)
#define POLYCC_META_LEAD(meta, oct) (((meta) >> (8u + 3u * (oct))) & 7u)

typedef struct polycc_normal {
    float nx, ny, nz; /* outward normal, |n| <= 1 */
} polycc_normal_t;

typedef struct polycc_plane {
    uint16_t normal; /* index into normals[] */
    int16_t d;       /* offset in quanta: g(p) = n . p - d * quantum */
} polycc_plane_t;

typedef struct polycc_poly {
    int16_t c[3];       /* culling centre (interior point), in quanta */
    uint16_t r_out;     /* outer culling radius in units of POLYCC_R_OUT_QUANTA quanta, rounded up */
    uint16_t r_in;      /* inner radius in quanta, rounded down */
    uint16_t inv_gamma; /* 1 / gamma in units of 2^-8, rounded up (>= 256) */
    uint32_t meta;      /* count - 1 (bits 0..7), lead plane per octant (3 bits each, from bit 8) */
} polycc_poly_t;

typedef struct polycc_cluster {
    uint16_t first;       /* first polytope in polys[] */
    uint16_t count;       /* number of polytopes */
    uint32_t first_plane; /* first plane of polys[first] in planes[] */
    float cx, cy, cz;     /* cluster centre */
    float r_out;          /* outer radius, rounded up */
    float inv_gamma;      /* max_k 1/gamma_k */
    float r_in;           /* reach, rounded up */
} polycc_cluster_t;

/* Spatial index (docs/barrier.md section 9): a uniform grid of cells of side s over the box B with low
 * corner (ox, oy, oz), each cell a leaf or an octree.  The kernel computes t = (p - o) * inv_cell in
 * float32, takes the cell floor(t) and its node v = cell_list[cell]; while v >= n_lists (an inner node)
 * it doubles t (exact) and descends to children[8 (v - n_lists) + octant], octant bit b = the parity of
 * floor(t_b).  A leaf v < n_lists names the list of polytopes the kernel evaluates there; psi0 is capped
 * at `cap` (D, metres); outside B it returns D with no polytope evaluated.  Certified by the generator
 * (polycc/onboard/index.py): every polytope left out of a leaf box has phi_k >= min(U_box, D) over it,
 * every polytope has phi_k >= D outside B. */
typedef struct polycc_index {
    float ox, oy, oz;              /* low corner of B, metres */
    float inv_cell;                /* 1 / s, a power of two */
    float cap;                     /* clearance cap D, metres (> 0) */
    uint16_t nx, ny, nz;           /* grid dimensions (>= 1); cell id = i + nx (j + ny k) */
    uint16_t n_lists;              /* number of distinct lists */
    uint32_t n_entries;            /* length of entries[] */
    uint32_t n_inner;              /* inner octree nodes: children[8 n_inner] */
    const uint16_t *cell_list;     /* [nx ny nz] node of each cell: < n_lists a list id, else inner node */
    const uint16_t *children;      /* [8 n_inner] the octants' nodes of each inner node */
    const uint16_t *list_start;    /* [n_lists + 1] list l is entries[list_start[l] .. list_start[l + 1]) */
    const uint16_t *entries;       /* polytope indices into polys[] */
    const uint16_t *poly_first;    /* [n_polys] first plane of each polytope */
} polycc_index_t;

typedef struct polycc_scene {
    uint32_t format;     /* POLYCC_SCENE_FORMAT */
    uint32_t n_clusters; /* number of clusters (>= 1 if n_polys > 0) */
    uint32_t n_polys;    /* number of polytopes */
    uint32_t n_planes;   /* number of half-planes */
    uint32_t n_normals;  /* number of normals */
    float quantum;       /* q, a power of two (metres) */
    float coord_bound;   /* rounding-margin scale, see above */
    float log_lmax;      /* >= ln(max half-planes per polytope) */
    const polycc_cluster_t *clusters;
    const polycc_poly_t *polys;
    const polycc_plane_t *planes;
    const polycc_normal_t *normals;
    const polycc_index_t *index; /* NULL: no index, every polytope is a candidate, no cap */
} polycc_scene_t;

#endif /* POLYCC_SCENE_LAYOUT_H */
