"""cffi (API mode) build of the on-board kernel: the same .c files the firmware compiles.

Flags: ``-O2 -ffp-contract=off -fno-math-errno -std=c99`` plus the strict warning set.  The
extension is built once per hash of (sources, flags, cffi version) in the build cache
(:func:`polycc.resources.cache_dir`, ``cffi/``) in a
private temporary directory and moved into place with ``os.replace``, so concurrent pytest
workers never see a half-written module.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from polycc import resources
from polycc.cbuild import build_cffi, source_hash  # noqa: F401  (source_hash: re-exported)
from polycc.onboard.barrier import Params
from polycc.onboard.layout import SCENE_FORMAT, PackedScene
from polycc.sim.cdef import headers_cdef

SRC = resources.firmware_src()
KERNEL_SOURCES = [SRC / "polycc_kernel.c"]
KERNEL_HEADERS = [SRC / "polycc_kernel.h", SRC / "polycc_scene_layout.h"]
HOST_CFLAGS = ["-O2", "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-Wall", "-Wextra", "-Wdouble-promotion",
               "-Wconversion", "-Werror"]

# The kernel's types, constants and API straight from its headers (polycc.sim.cdef), plus the
# host-only batch loops below.
CDEF = headers_cdef(SRC / "polycc_scene_layout.h", SRC / "polycc_kernel.h") + """
void polycc_host_step_batch(const polycc_scene_t *scene, const polycc_params_t *params, const float *x,
                            const float *goal, size_t n, polycc_out_t *out);
void polycc_host_exp_batch(const float *x, size_t n, float *y);
void polycc_host_log_batch(const float *x, size_t n, float *y);
"""

# Host-only batch loops (not part of the firmware); they only call the kernel's public API.
BATCH_SOURCE = """
#include <stddef.h>
#include "polycc_kernel.h"
void polycc_host_step_batch(const polycc_scene_t *scene, const polycc_params_t *params, const float *x,
                            const float *goal, size_t n, polycc_out_t *out)
{
    size_t i;
    for (i = 0; i < n; ++i) {
        (void)polycc_step(scene, params, x + 3 * i, goal + 3 * i, out + i);
    }
}
void polycc_host_exp_batch(const float *x, size_t n, float *y)
{
    size_t i;
    for (i = 0; i < n; ++i) {
        y[i] = polycc_exp(x[i]);
    }
}
void polycc_host_log_batch(const float *x, size_t n, float *y)
{
    size_t i;
    for (i = 0; i < n; ++i) {
        y[i] = polycc_log(x[i]);
    }
}
"""

OUT_DTYPE = np.dtype([("u", "<f4", 3), ("u_nom", "<f4", 3), ("psi", "<f4"), ("grad", "<f4", 3), ("flags", "<u4")])


@lru_cache(maxsize=1)
def load():
    """Build (if needed) and import the kernel extension; returns the cffi ``lib``/``ffi`` module."""
    return build_cffi("_polycc_kernel", CDEF, BATCH_SOURCE, KERNEL_SOURCES + KERNEL_HEADERS, [SRC], HOST_CFLAGS)


@dataclass
class HostScene:
    """A ``polycc_scene_t`` built in host memory from a :class:`PackedScene` (keeps buffers alive)."""

    packed: PackedScene
    fmt: int = SCENE_FORMAT

    def __post_init__(self):
        m = load()
        ffi = m.ffi
        self._clusters = np.ascontiguousarray(self.packed.clusters)
        self._polys = np.ascontiguousarray(self.packed.polys_raw)
        self._planes = np.ascontiguousarray(self.packed.planes)
        self._normals = np.ascontiguousarray(self.packed.normals)
        self.c = ffi.new("polycc_scene_t *")
        self.c.format = self.fmt
        self.c.n_clusters = self.packed.n_clusters
        self.c.n_polys = self.packed.n_polys
        self.c.n_planes = self.packed.n_planes
        self.c.n_normals = self.packed.n_normals
        self.c.quantum = float(self.packed.quantum)
        self.c.coord_bound = float(self.packed.coord_bound)
        self.c.log_lmax = float(self.packed.log_lmax)
        # empty arrays: a valid non-NULL pointer (the kernel never reads it)
        keep = self._keep = [a if a.nbytes else np.zeros(1, np.uint32) for a in
                             (self._clusters, self._polys, self._planes, self._normals)]
        self.c.clusters = ffi.cast("const polycc_cluster_t *", ffi.from_buffer(keep[0]))
        self.c.polys = ffi.cast("const polycc_poly_t *", ffi.from_buffer(keep[1]))
        self.c.planes = ffi.cast("const polycc_plane_t *", ffi.from_buffer(keep[2]))
        self.c.normals = ffi.cast("const polycc_normal_t *", ffi.from_buffer(keep[3]))
        self.c.index = ffi.NULL
        ix = self.packed.index
        if ix is not None:
            self._ix = ffi.new("polycc_index_t *")
            for k, v in ix.record().items():
                setattr(self._ix, k, float(v) if isinstance(v, np.floating) else int(v))
            self._ix_arrays = [np.ascontiguousarray(a, np.uint16) if len(a) else np.zeros(2, np.uint16)
                               for a in ix.arrays()]
            for name, a in zip(("cell_list", "children", "list_start", "entries", "poly_first"), self._ix_arrays):
                setattr(self._ix, name, ffi.cast("const uint16_t *", ffi.from_buffer(a)))
            self.c.index = self._ix


def c_params(params: Params):
    ffi = load().ffi
    p = ffi.new("polycc_params_t *")
    p.kappa, p.radius, p.beta, p.c_clf, p.v_max = (float(v) for v in params.f32())
    return p


def step_batch(scene: HostScene, params: Params, x: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Run ``polycc_step`` for every row; returns a structured array (OUT_DTYPE)."""
    m = load()
    ffi = m.ffi
    x = np.ascontiguousarray(np.asarray(x, np.float32).reshape(-1, 3))
    goal = np.ascontiguousarray(np.broadcast_to(np.asarray(goal, np.float32).reshape(-1, 3), x.shape))
    out = np.zeros(len(x), OUT_DTYPE)
    assert OUT_DTYPE.itemsize == ffi.sizeof("polycc_out_t")
    m.lib.polycc_host_step_batch(scene.c, c_params(params), ffi.cast("const float *", ffi.from_buffer(x)),
                                 ffi.cast("const float *", ffi.from_buffer(goal)), len(x),
                                 ffi.cast("polycc_out_t *", ffi.from_buffer(out)))
    return out


# A generated polytopes.h compiled with the kernel: the scene the C reads is the header's own
# `polycc_scene`, and its bytes can be dumped for comparison with PackedScene.to_bytes().
GENERATED_CDEF = CDEF + """
const polycc_scene_t *polycc_generated_scene(void);
size_t polycc_generated_image(unsigned char *out, size_t cap);
"""
GENERATED_SOURCE = """
#include <string.h>
#include "polytopes.h"
""" + BATCH_SOURCE + """
const polycc_scene_t *polycc_generated_scene(void) { return &polycc_scene; }
/* The flat image of PackedScene.to_bytes(): 8 header words, clusters, polys, planes, normals, then the
 * index (its 9 header words and five uint16 arrays, each padded to 4 bytes) if there is one. */
#define PAD4(n) (((n) * 2u + 3u) / 4u * 4u)
size_t polycc_generated_image(unsigned char *out, size_t cap)
{
    const polycc_scene_t *s = &polycc_scene;
    const polycc_index_t *ix = s->index;
    size_t parts[11], n = 0, i, np = 5u;
    const void *src[11];
    src[0] = s; parts[0] = 8u * 4u;
    src[1] = s->clusters; parts[1] = s->n_clusters * sizeof(polycc_cluster_t);
    src[2] = s->polys; parts[2] = s->n_polys * sizeof(polycc_poly_t);
    src[3] = s->planes; parts[3] = s->n_planes * sizeof(polycc_plane_t);
    src[4] = s->normals; parts[4] = s->n_normals * sizeof(polycc_normal_t);
    if (ix != NULL) {
        src[5] = ix; parts[5] = 9u * 4u;
        src[6] = ix->cell_list; parts[6] = PAD4((size_t)ix->nx * ix->ny * ix->nz);
        src[7] = ix->children; parts[7] = PAD4((size_t)ix->n_inner * 8u);
        src[8] = ix->list_start; parts[8] = PAD4((size_t)ix->n_lists + 1u);
        src[9] = ix->entries; parts[9] = PAD4((size_t)ix->n_entries);
        src[10] = ix->poly_first; parts[10] = PAD4((size_t)s->n_polys);
        np = 11u;
    }
    for (i = 0; i < np; ++i) {
        if (out != NULL && n + parts[i] <= cap) {
            memcpy(out + n, src[i], parts[i]);
        }
        n += parts[i];
    }
    return n;
}
"""


def load_generated(header: Path):
    """Build (once per header content) and import the kernel compiled together with a generated
    ``polytopes.h`` (same flags as :func:`load`); race-safe under pytest-xdist like :func:`load`."""
    header = Path(header)
    text = header.read_bytes()

    def prepare(tmp: Path):
        inc = tmp / "generated"
        inc.mkdir()
        (inc / "polytopes.h").write_bytes(text)
        return [inc]

    return build_cffi("_polycc_gen", GENERATED_CDEF, GENERATED_SOURCE, KERNEL_SOURCES + KERNEL_HEADERS, [SRC],
                      HOST_CFLAGS, key_parts=[text], prepare=prepare)


def generated_image(mod) -> bytes:
    """The bytes the generated header holds, in PackedScene.to_bytes() order."""
    n = mod.lib.polycc_generated_image(mod.ffi.NULL, 0)
    buf = mod.ffi.new("unsigned char[]", n)
    assert mod.lib.polycc_generated_image(buf, n) == n
    return bytes(mod.ffi.buffer(buf, n))


def generated_step_batch(mod, params: Params, x: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """``polycc_step`` on the generated header's own ``polycc_scene`` for every row (OUT_DTYPE)."""
    ffi = mod.ffi
    p = ffi.new("polycc_params_t *")
    p.kappa, p.radius, p.beta, p.c_clf, p.v_max = (float(v) for v in params.f32())
    x = np.ascontiguousarray(np.asarray(x, np.float32).reshape(-1, 3))
    goal = np.ascontiguousarray(np.broadcast_to(np.asarray(goal, np.float32).reshape(-1, 3), x.shape))
    out = np.zeros(len(x), OUT_DTYPE)
    assert OUT_DTYPE.itemsize == ffi.sizeof("polycc_out_t")
    mod.lib.polycc_host_step_batch(mod.lib.polycc_generated_scene(), p, ffi.cast("const float *", ffi.from_buffer(x)),
                                   ffi.cast("const float *", ffi.from_buffer(goal)), len(x),
                                   ffi.cast("polycc_out_t *", ffi.from_buffer(out)))
    return out


def _unary_batch(fn_name: str, x: np.ndarray) -> np.ndarray:
    m = load()
    ffi = m.ffi
    x = np.ascontiguousarray(np.asarray(x, np.float32).ravel())
    y = np.empty_like(x)
    getattr(m.lib, fn_name)(ffi.cast("const float *", ffi.from_buffer(x)), len(x),
                            ffi.cast("float *", ffi.from_buffer(y)))
    return y


def exp_batch(x: np.ndarray) -> np.ndarray:
    return _unary_batch("polycc_host_exp_batch", x)


def log_batch(x: np.ndarray) -> np.ndarray:
    return _unary_batch("polycc_host_log_batch", x)
