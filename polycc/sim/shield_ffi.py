"""cffi (API mode) build of the shield (firmware_app/src/polycc_shield.c) with the kernel, for the
bit-exactness tests and the bench: the same .c files and flags as :mod:`polycc.sim.kernel_ffi`.

``run_batch(host_scene, params, rows)`` runs ``polycc_shield_run`` once per row of 15 float32
(p, v, a0, u_app, u_d; m, m/s, m/s^2) and returns OUT_DTYPE records.  ``host_scene`` is a
:class:`polycc.sim.kernel_ffi.HostScene` (its ``polycc_scene_t`` is passed by address).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from polycc.onboard.shield import ShieldParams
from polycc.sim.cdef import headers_cdef
from polycc.sim.kernel_ffi import HOST_CFLAGS, KERNEL_HEADERS, KERNEL_SOURCES, SRC, build_cffi

SHIELD_SOURCES = [SRC / "polycc_shield.c"]
SHIELD_HEADERS = [SRC / "polycc_shield.h"]

CDEF = headers_cdef(SRC / "polycc_scene_layout.h", SRC / "polycc_kernel.h", SRC / "polycc_shield.h") + """
typedef struct polycc_host_shield_out {
    float u_c[3]; float u_d[3]; float a_end[3]; float psi; float grad[3]; float c; float min_c;
    uint32_t n; uint32_t i; uint32_t cov; uint32_t evals; uint32_t flags;
} polycc_host_shield_out_t;
void polycc_host_shield_batch(const polycc_scene_t *scene, const polycc_shield_params_t *prm, const float *rows,
                              size_t n, polycc_host_shield_out_t *out, float *x_last);
"""

BATCH_SOURCE = """
#include <stddef.h>
#include <string.h>
#include "polycc_shield.h"
typedef struct polycc_host_shield_out {
    float u_c[3]; float u_d[3]; float a_end[3]; float psi; float grad[3]; float c; float min_c;
    uint32_t n; uint32_t i; uint32_t cov; uint32_t evals; uint32_t flags;
} polycc_host_shield_out_t;
static polycc_shield_job_t job;
void polycc_host_shield_batch(const polycc_scene_t *scene, const polycc_shield_params_t *prm, const float *rows,
                              size_t n, polycc_host_shield_out_t *out, float *x_last)
{
    size_t k;
    for (k = 0; k < n; ++k) {
        const float *r = rows + 15 * k;
        polycc_host_shield_out_t *o = out + k;
        (void)polycc_shield_run(&job, scene, prm, r, r + 3, r + 6, r + 9, r + 12);
        memcpy(o->u_c, job.u_c, sizeof o->u_c);
        memcpy(o->u_d, job.u_d, sizeof o->u_d);
        memcpy(o->a_end, job.a_end, sizeof o->a_end);
        o->psi = job.psi;
        memcpy(o->grad, job.grad, sizeof o->grad);
        o->c = job.c;
        o->min_c = job.min_c;
        o->n = job.n; o->i = job.i; o->cov = job.cov; o->evals = job.evals; o->flags = job.flags;
        memcpy(x_last + 3 * k, job.x[job.n], 3 * sizeof(float));
    }
}
"""

OUT_DTYPE = np.dtype([("u_c", "<f4", 3), ("u_d", "<f4", 3), ("a_end", "<f4", 3), ("psi", "<f4"), ("grad", "<f4", 3),
                      ("c", "<f4"), ("min_c", "<f4"), ("n", "<u4"), ("i", "<u4"), ("cov", "<u4"), ("evals", "<u4"),
                      ("flags", "<u4")])
FLOAT_FIELDS = ("u_c", "u_d", "a_end", "psi", "grad", "c", "min_c")
INT_FIELDS = ("n", "i", "cov", "evals", "flags")


@lru_cache(maxsize=1)
def load():
    return build_cffi("_polycc_shield", CDEF, BATCH_SOURCE, KERNEL_SOURCES + SHIELD_SOURCES + KERNEL_HEADERS
                      + SHIELD_HEADERS, [SRC], HOST_CFLAGS)


def c_params(prm: ShieldParams):
    m = load()
    p = m.ffi.new("polycc_shield_params_t *")
    for name, value in prm.f32().items():
        setattr(p, name, int(value) if isinstance(value, int) else float(value))
    return p


def run_batch(host_scene, prm: ShieldParams, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``polycc_shield_run`` per row; returns (OUT_DTYPE records, the model's last point per row)."""
    m = load()
    ffi = m.ffi
    rows = np.ascontiguousarray(np.asarray(rows, np.float32).reshape(-1, 15))
    out = np.zeros(len(rows), OUT_DTYPE)
    last = np.zeros((len(rows), 3), np.float32)
    assert OUT_DTYPE.itemsize == ffi.sizeof("polycc_host_shield_out_t")
    from polycc.sim import kernel_ffi

    addr = int(kernel_ffi.load().ffi.cast("uintptr_t", host_scene.c))  # the same struct, another cffi module
    scene = ffi.cast("const polycc_scene_t *", addr)
    m.lib.polycc_host_shield_batch(scene, c_params(prm), ffi.cast("const float *", ffi.from_buffer(rows)), len(rows),
                                   ffi.cast("polycc_host_shield_out_t *", ffi.from_buffer(out)),
                                   ffi.cast("float *", ffi.from_buffer(last)))
    return out, last


# ---------------------------------------------------------------- Cortex-M4 (QEMU)
ARM_DTYPE = np.dtype(OUT_DTYPE.descr + [("x_last", "<f4", 3)])


def arm_program():
    """The semihosting shield test program (polycc/sim/arm/shield_main.c) built with the firmware's
    Cortex-M4 flags; returns the ELF path."""
    from polycc.sim import kernel_arm as KA

    srcs = [KA.ARM_DIR / "shield_main.c", KA.ARM_DIR / "startup.c", KA.ARM_DIR / "semihost.c", *SHIELD_SOURCES]
    heads = [KA.ARM_DIR / "semihost.h", KA.ARM_DIR / "scene_image.h", *SHIELD_HEADERS]
    return KA.build("shield_test", srcs, extra_headers=heads) / "shield_test.elf"


def arm_run(elf, scene, prm: ShieldParams, rows: np.ndarray, timeout: float = 600.0) -> np.ndarray:
    """``polycc_shield_run`` per row inside qemu-system-arm; returns ARM_DTYPE records."""
    import subprocess
    import tempfile
    from pathlib import Path

    from polycc.errors import PolyccError
    from polycc.sim import kernel_arm as KA

    rows = np.ascontiguousarray(np.asarray(rows, np.float32).reshape(-1, 15))
    q = prm.f32()
    floats = [q[k] for k in q if not isinstance(q[k], int)]
    ints = [q[k] for k in q if isinstance(q[k], int)]
    head = np.array(floats, np.float32).tobytes() + np.array(ints, np.uint32).tobytes()
    assert len(head) == load().ffi.sizeof("polycc_shield_params_t")
    with tempfile.TemporaryDirectory(prefix="polycc-qemu-shield-") as d:
        d = Path(d)
        (d / "scene.bin").write_bytes(scene.to_bytes())
        (d / "shield.bin").write_bytes(head + np.uint32(len(rows)).tobytes() + rows.tobytes())
        cmd = [KA.QEMU, "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-serial", "none",
               "-semihosting-config", "enable=on,target=native", "-kernel", str(elf)]
        r = subprocess.run(cmd, cwd=d, capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0:
            raise PolyccError(f"qemu run failed (exit {r.returncode}): {(r.stdout + r.stderr).strip()[:300]}")
        return np.frombuffer((d / "out.bin").read_bytes(), ARM_DTYPE).copy()
