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
#include "scene_image.h"
#include "semihost.h"

#define SCENE_MAX (96u * 1024u)
#define CHUNK 16u

static uint32_t scene_buf[SCENE_MAX / 4u];
static float in_buf[6u];
static polycc_swarm_t sw_buf;
static polycc_out_t out_buf[CHUNK];

int main(void)
{
    polycc_scene_t scene;
    polycc_params_t params;
    float v_nbr;
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
    if (fi < 0 || fo < 0 || !semihost_read_all(fi, &params, sizeof params) || !semihost_read_all(fi, &v_nbr, sizeof v_nbr) ||
        !semihost_read_all(fi, &n, sizeof n)) {
        semihost_puts("cannot open states.bin/out.bin\n");
        return 3;
    }
    while (done < n) {
        uint32_t k, m = n - done < CHUNK ? n - done : CHUNK;
        for (k = 0; k < m; ++k) {
            if (!semihost_read_all(fi, in_buf, 6u * sizeof(float)) || !semihost_read_all(fi, &sw_buf, sizeof sw_buf)) {
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
