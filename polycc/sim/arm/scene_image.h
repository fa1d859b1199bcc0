/*
 * scene_image.h -- the ARM test harnesses' reader of the flat scene image (scene.bin) written by
 * polycc/onboard/layout.py PackedScene.to_bytes(): 8 header words, clusters, polys, planes, normals,
 * then optionally the spatial index (9 header words and five uint16 arrays, each padded to 4 bytes).
 * Shared by main.c, shield_main.c and swarm_main.c.  The image stays in `buf`; nothing is copied.
 */
#ifndef POLYCC_SCENE_IMAGE_H
#define POLYCC_SCENE_IMAGE_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "polycc_scene_layout.h"

#define POLYCC_IMAGE_PAD4(n) ((((uint32_t)(n)) * 2u + 3u) / 4u * 4u)

/* Fills *scene (and *ix when the image holds an index) from the image of `len` bytes at buf (4-byte
 * aligned).  Returns 0, or 1 when the image is shorter than its header says. */
static int polycc_scene_from_image(polycc_scene_t *scene, polycc_index_t *ix, const uint32_t *buf, size_t len)
{
    uint32_t head[8];
    const uint8_t *base = (const uint8_t *)buf, *end = base + len;
    if (len < sizeof head) {
        return 1;
    }
    memcpy(head, buf, sizeof head);
    scene->format = head[0];
    scene->n_clusters = head[1];
    scene->n_polys = head[2];
    scene->n_planes = head[3];
    scene->n_normals = head[4];
    memcpy(&scene->quantum, &head[5], 4);
    memcpy(&scene->coord_bound, &head[6], 4);
    memcpy(&scene->log_lmax, &head[7], 4);
    base += sizeof head;
    scene->clusters = (const polycc_cluster_t *)(const void *)base;
    base += POLYCC_CLUSTER_BYTES * scene->n_clusters;
    scene->polys = (const polycc_poly_t *)(const void *)base;
    base += POLYCC_POLY_BYTES * scene->n_polys;
    scene->planes = (const polycc_plane_t *)(const void *)base;
    base += POLYCC_PLANE_BYTES * scene->n_planes;
    scene->normals = (const polycc_normal_t *)(const void *)base;
    base += POLYCC_NORMAL_BYTES * scene->n_normals;
    scene->index = NULL;
    if (base > end) {
        return 1;
    }
    if (base + 36 <= end) {
        memcpy(ix, base, 36); /* ox, oy, oz, inv_cell, cap, nx, ny, nz, n_lists, n_entries, n_inner */
        base += 36;
        ix->cell_list = (const uint16_t *)(const void *)base;
        base += POLYCC_IMAGE_PAD4((uint32_t)ix->nx * ix->ny * ix->nz);
        ix->children = (const uint16_t *)(const void *)base;
        base += POLYCC_IMAGE_PAD4(8u * ix->n_inner);
        ix->list_start = (const uint16_t *)(const void *)base;
        base += POLYCC_IMAGE_PAD4((uint32_t)ix->n_lists + 1u);
        ix->entries = (const uint16_t *)(const void *)base;
        base += POLYCC_IMAGE_PAD4(ix->n_entries);
        ix->poly_first = (const uint16_t *)(const void *)base;
        base += POLYCC_IMAGE_PAD4(scene->n_polys);
        if (base > end) {
            return 1;
        }
        scene->index = ix;
    }
    return 0;
}

#endif /* POLYCC_SCENE_IMAGE_H */
