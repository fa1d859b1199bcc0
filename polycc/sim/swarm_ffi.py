"""cffi (API mode) host build of ``polycc_swarm.c`` + the kernel, with the kernel's host flags
(``-ffp-contract=off``, ``-Wconversion -Werror``), for the bit-exactness tests and benchmarks.

    mod = load();  sc = host_scene(mod, packed)
    sw = mod.ffi.new("polycc_swarm_t *");  mod.lib.polycc_swarm_report(sw, id, p_j, age_ms, r_j, p0)
    out = mod.ffi.new("polycc_out_t *");   mod.lib.polycc_swarm_step(sc.c, prm, sw, v, x, goal, out)
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from polycc import resources
from polycc.cbuild import build_cffi
from polycc.onboard.barrier import Params
from polycc.sim.cdef import headers_cdef
from polycc.sim.kernel_ffi import HOST_CFLAGS, KERNEL_HEADERS, KERNEL_SOURCES, HostScene

SRC = resources.firmware_src()
SOURCES = KERNEL_SOURCES + [SRC / "polycc_swarm.c"]
HEADERS = KERNEL_HEADERS + [SRC / "polycc_swarm.h"]
CDEF = headers_cdef(SRC / "polycc_scene_layout.h", SRC / "polycc_kernel.h", SRC / "polycc_swarm.h")
GLUE = '#include "polycc_swarm.h"\n'


@lru_cache(maxsize=1)
def load():
    """Build (if needed) and import the swarm extension (``lib``/``ffi``)."""
    return build_cffi("_polycc_swarm", CDEF, GLUE, SOURCES + HEADERS, [SRC], HOST_CFLAGS)


class SwarmScene(HostScene):
    """A :class:`HostScene` whose ``polycc_scene_t`` lives in the swarm module's ffi."""

    def __post_init__(self):
        ffi = load().ffi
        keep = self._keep = [np.ascontiguousarray(a) if a.nbytes else np.zeros(1, np.uint32) for a in
                             (self.packed.clusters, self.packed.polys_raw, self.packed.planes, self.packed.normals)]
        self.c = ffi.new("polycc_scene_t *")
        self.c.format = self.fmt
        self.c.n_clusters = self.packed.n_clusters
        self.c.n_polys = self.packed.n_polys
        self.c.n_planes = self.packed.n_planes
        self.c.n_normals = self.packed.n_normals
        self.c.quantum = float(self.packed.quantum)
        self.c.coord_bound = float(self.packed.coord_bound)
        self.c.log_lmax = float(self.packed.log_lmax)
        for name, a, t in zip(("clusters", "polys", "planes", "normals"), keep,
                              ("cluster", "poly", "plane", "normal")):
            setattr(self.c, name, ffi.cast(f"const polycc_{t}_t *", ffi.from_buffer(a)))


def c_params(params: Params):
    p = load().ffi.new("polycc_params_t *")
    p.kappa, p.radius, p.beta, p.c_clf, p.v_max = (float(v) for v in params.f32())
    return p


def f3(v):
    return load().ffi.new("float[3]", [float(a) for a in np.asarray(v, np.float32).reshape(3)])


def step(scene: SwarmScene, params: Params, sw, v_nbr: float, x, goal) -> dict:
    """``polycc_swarm_step`` for one state; the same dict as :func:`polycc.onboard.swarm.step`."""
    m = load()
    out = m.ffi.new("polycc_out_t *")
    m.lib.polycc_swarm_step(scene.c, c_params(params), sw, float(np.float32(v_nbr)), f3(x), f3(goal), out)
    return {"u": np.array(list(out.u), np.float32), "u_nom": np.array(list(out.u_nom), np.float32),
            "psi": np.float32(out.psi), "grad": np.array(list(out.grad), np.float32), "flags": np.uint32(out.flags)}
