/*
 * Bare-metal bit-exactness test of the polycc shield (qemu -M netduinoplus2, semihosting).
 *
 * Reads  scene.bin   the flat scene image of polycc/onboard/layout.py
 *        shield.bin  polycc_shield_params_t (76 bytes), uint32 n, then n rows of 15 floats
 *                    (p, v, a0, u_app, u_d)
 * Writes out.bin     n records: u_c[3] u_d[3] a_end[3] psi grad[3] c min_c (floats), n i cov evals flags
 *                    (uint32), x_n[3] (floats) -- polycc/sim/shield_ffi.py ARM_DTYPE.
 * Exit code 0 on success.
 */
#include <stdint.h>
#include <string.h>

#include "polycc_shield.h"
#include "scene_image.h"
#include "semihost.h"

#define SCENE_MAX (96u * 1024u)

typedef struct rec {
    float u_c[3], u_d[3], a_end[3], psi, grad[3], c, min_c;
    uint32_t n, i, cov, evals, flags;
    float x_last[3];
} rec_t;

static uint32_t scene_buf[SCENE_MAX / 4u];
static polycc_shield_job_t job;

int main(void)
{
    polycc_scene_t scene;
    polycc_shield_params_t params;
    polycc_index_t index;
    uint32_t n, done = 0;
    int fi, fo, got;

    got = semihost_slurp("scene.bin", scene_buf, sizeof scene_buf);
    if (got < 0 || polycc_scene_from_image(&scene, &index, scene_buf, (size_t)got) != 0) {
        semihost_puts("cannot read scene.bin\n");
        return 2;
    }

    fi = semihost_open("shield.bin", 1);
    fo = semihost_open("out.bin", 5);
    if (fi < 0 || fo < 0 || !semihost_read_all(fi, &params, sizeof params) || !semihost_read_all(fi, &n, sizeof n)) {
        semihost_puts("cannot open shield.bin/out.bin\n");
        return 3;
    }
    while (done < n) {
        float r[15];
        rec_t o;
        if (!semihost_read_all(fi, r, sizeof r)) {
            semihost_puts("short shield.bin\n");
            return 4;
        }
        (void)polycc_shield_run(&job, &scene, &params, r, r + 3, r + 6, r + 9, r + 12);
        memcpy(o.u_c, job.u_c, sizeof o.u_c);
        memcpy(o.u_d, job.u_d, sizeof o.u_d);
        memcpy(o.a_end, job.a_end, sizeof o.a_end);
        o.psi = job.psi;
        memcpy(o.grad, job.grad, sizeof o.grad);
        o.c = job.c;
        o.min_c = job.min_c;
        o.n = job.n;
        o.i = job.i;
        o.cov = job.cov;
        o.evals = job.evals;
        o.flags = job.flags;
        memcpy(o.x_last, job.x[job.n], sizeof o.x_last);
        if (semihost_write(fo, &o, sizeof o) != 0) {
            semihost_puts("cannot write out.bin\n");
            return 5;
        }
        done += 1u;
    }
    semihost_close(fi);
    semihost_close(fo);
    return 0;
}
