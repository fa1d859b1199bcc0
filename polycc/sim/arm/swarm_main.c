/*
 * Bare-metal bit-exactness test of polycc_swarm_step (qemu -M netduinoplus2, semihosting).
 *
 * Reads  scene.bin   the flat scene image of polycc/onboard/layout.py
 *        states.bin  5 float params, float v_nbr, uint32 n, then n records of 6 floats (x[3], goal[3])
 *                    followed by one polycc_swarm_t image (the neighbour table)
 * Writes out.bin     n polycc_out_t records, exactly as polycc_swarm_step filled them.
 * Exit code 0 on success.
 */
#include <stdint.h>
#include <string.h>

#include "polycc_swarm.h"
#include "semihost.h"

#define SCENE_MAX (96u * 1024u)
#define CHUNK 16u

static uint32_t scene_buf[SCENE_MAX / 4u];
static float in_buf[6u];
static polycc_swarm_t sw_buf;
static polycc_out_t out_buf[CHUNK];

static int read_all(int fd, void *buf, size_t n)
{
    return semihost_read(fd, buf, n) == (int)n;
}

int main(void)
{
    polycc_scene_t scene;
    polycc_params_t params;
    float v_nbr;
    uint32_t head[8], n, done = 0;
    const uint8_t *base = (const uint8_t *)scene_buf;
    int fs, fi, fo;

    fs = semihost_open("scene.bin", 1);
    if (fs < 0 || semihost_read(fs, scene_buf, sizeof scene_buf) < (int)sizeof head) {
        semihost_puts("cannot read scene.bin\n");
        return 2;
    }
    semihost_close(fs);
    memcpy(head, scene_buf, sizeof head);
    scene.format = head[0];
    scene.n_clusters = head[1];
    scene.n_polys = head[2];
    scene.n_planes = head[3];
    scene.n_normals = head[4];
    memcpy(&scene.quantum, &head[5], 4);
    memcpy(&scene.coord_bound, &head[6], 4);
    memcpy(&scene.log_lmax, &head[7], 4);
    base += sizeof head;
    scene.clusters = (const polycc_cluster_t *)(const void *)base;
    base += POLYCC_CLUSTER_BYTES * scene.n_clusters;
    scene.polys = (const polycc_poly_t *)(const void *)base;
    base += POLYCC_POLY_BYTES * scene.n_polys;
    scene.planes = (const polycc_plane_t *)(const void *)base;
    base += POLYCC_PLANE_BYTES * scene.n_planes;
    scene.normals = (const polycc_normal_t *)(const void *)base;

    fi = semihost_open("states.bin", 1);
    fo = semihost_open("out.bin", 5);
    if (fi < 0 || fo < 0 || !read_all(fi, &params, sizeof params) || !read_all(fi, &v_nbr, sizeof v_nbr) ||
        !read_all(fi, &n, sizeof n)) {
        semihost_puts("cannot open states.bin/out.bin\n");
        return 3;
    }
    while (done < n) {
        uint32_t k, m = n - done < CHUNK ? n - done : CHUNK;
        for (k = 0; k < m; ++k) {
            if (!read_all(fi, in_buf, 6u * sizeof(float)) || !read_all(fi, &sw_buf, sizeof sw_buf)) {
                semihost_puts("short states.bin\n");
                return 4;
            }
            (void)polycc_swarm_step(&scene, &params, &sw_buf, v_nbr, &in_buf[0], &in_buf[3], &out_buf[k]);
        }
        if (semihost_write(fo, out_buf, m * sizeof(polycc_out_t)) != 0) {
            semihost_puts("cannot write out.bin\n");
            return 5;
        }
        done += m;
    }
    semihost_close(fi);
    semihost_close(fo);
    return 0;
}
