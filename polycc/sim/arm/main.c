/*
 * Bare-metal bit-exactness test of the polycc kernel (qemu -M netduinoplus2, semihosting).
 *
 * Reads  scene.bin   the flat scene image of polycc/onboard/layout.py (header, clusters, polys, planes,
 *                    normals)
 *        states.bin  5 float params (kappa, radius, beta, c_clf, v_max), uint32 n, then n records
 *                    of 6 floats (x[3], goal[3])
 * Writes out.bin     n polycc_out_t records (44 bytes each), exactly as the kernel filled them.
 * Exit code 0 on success.
 */
#include <stdint.h>
#include <string.h>

#include "polycc_kernel.h"
#include "scene_image.h"
#include "semihost.h"

#define SCENE_MAX (112u * 1024u)
#define CHUNK 64u

static uint32_t scene_buf[SCENE_MAX / 4u];
static float in_buf[CHUNK * 6u];
static polycc_out_t out_buf[CHUNK];

int main(void)
{
    polycc_scene_t scene;
    polycc_params_t params;
    polycc_index_t index;
    uint32_t n, done = 0;
    int fi, fo, got;

    got = semihost_slurp("scene.bin", scene_buf, sizeof scene_buf);
    if (got < 0 || polycc_scene_from_image(&scene, &index, scene_buf, (size_t)got) != 0) {
        semihost_puts("cannot read scene.bin\n");
        return 2;
    }

    fi = semihost_open("states.bin", 1);
    fo = semihost_open("out.bin", 5);
    if (fi < 0 || fo < 0 || !semihost_read_all(fi, &params, sizeof params) || !semihost_read_all(fi, &n, sizeof n)) {
        semihost_puts("cannot open states.bin/out.bin\n");
        return 3;
    }
    while (done < n) {
        uint32_t k, m = n - done < CHUNK ? n - done : CHUNK;
        if (!semihost_read_all(fi, in_buf, m * 6u * sizeof(float))) {
            semihost_puts("short states.bin\n");
            return 4;
        }
        for (k = 0; k < m; ++k) {
            (void)polycc_step(&scene, &params, &in_buf[6u * k], &in_buf[6u * k + 3u], &out_buf[k]);
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
