"""cffi build of ``polycc_plan.c`` (grid A* and the certified field's soft-min sums), host only.

Hand-written in C because the libraries measured are too slow on the 1.5M-splat room's grid
(203 x 203 x 55 cells, 26-connected): ``skimage.graph.MCP_Geometric`` needs 10 s per query (no
heuristic, no early exit), ``scipy.sparse.csgraph.dijkstra`` 18 s to build the 27M-edge graph and
20 s per query; the per-polytope field loop in numpy took 93 s. Built once per source hash into
the build cache by :func:`polycc.cbuild.build_cffi`.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from polycc.cbuild import build_cffi
from polycc.errors import PolyccError

HERE = Path(__file__).resolve().parent
SOURCES = [HERE / "polycc_plan.c", HERE / "polycc_plan.h"]
CFLAGS = ["-O2", "-std=c99", "-ffp-contract=off", "-Wall", "-Wextra", "-Wconversion", "-Werror"]


def _cdef() -> str:
    text = (HERE / "polycc_plan.h").read_text()
    out, keep = [], False
    for line in text.splitlines():  # the prototypes only (cffi does not take the preprocessor lines)
        if line.startswith(("int polycc_", "void polycc_")):
            keep = True
        if keep:
            out.append(line)
            if line.rstrip().endswith(";"):
                keep = False
    return "\n".join(out) + "\n"


@lru_cache(maxsize=1)
def load():
    """Build (if needed) and import the extension; returns the cffi module."""
    return build_cffi("_polycc_plan", _cdef(), '#include "polycc_plan.h"\n', SOURCES, [HERE], CFLAGS)


def _ptr(ffi, ctype: str, a: np.ndarray):
    return ffi.cast(ctype, ffi.from_buffer(a))


def astar(free: np.ndarray, spacing: float, src: np.ndarray, src_cost: np.ndarray, dst: np.ndarray,
          dst_cost: np.ndarray, goal_cell, shift: float, weight: float = 1.0):
    """A* on the 26-connected grid ``free`` (bool/uint8, C order) from the flat cells ``src``
    (start costs ``src_cost``, m) to the virtual goal reached from the flat cells ``dst`` at
    ``dst_cost``. Returns (cost m, flat cell path from a source to the target, cells expanded),
    cost = inf and an empty path when no path exists."""
    m = load()
    ffi, lib = m.ffi, m.lib
    free = np.ascontiguousarray(free, np.uint8)
    nx, ny, nz = free.shape
    n = free.size
    order = np.argsort(dst, kind="stable")
    dst = np.ascontiguousarray(np.asarray(dst, np.int64)[order])
    dst_cost = np.ascontiguousarray(np.asarray(dst_cost, np.float64)[order])
    src = np.ascontiguousarray(src, np.int64)
    src_cost = np.ascontiguousarray(src_cost, np.float64)
    g = np.full(n + 1, np.inf)
    parent = np.full(n, -1, np.int64)
    info = np.zeros(3, np.int64)
    rc = lib.polycc_astar(_ptr(ffi, "const uint8_t *", free), nx, ny, nz, float(spacing),
                          _ptr(ffi, "const int64_t *", src), _ptr(ffi, "const double *", src_cost), len(src),
                          _ptr(ffi, "const int64_t *", dst), _ptr(ffi, "const double *", dst_cost), len(dst),
                          int(goal_cell[0]), int(goal_cell[1]), int(goal_cell[2]), float(shift), float(weight),
                          _ptr(ffi, "double *", g), _ptr(ffi, "int64_t *", parent), _ptr(ffi, "int64_t *", info))
    if rc < 0:
        raise PolyccError(f"the planner ran out of memory on a {nx} x {ny} x {nz} grid; use a coarser --grid")
    if rc == 1:
        return np.inf, np.zeros(0, np.int64), int(info[1])
    path = [int(info[0])]
    while parent[path[-1]] >= 0:
        path.append(int(parent[path[-1]]))
    return float(g[n]), np.asarray(path[::-1], np.int64), int(info[1])


def field_sums(planes: np.ndarray, first: np.ndarray, count: np.ndarray, c: np.ndarray, blocks: np.ndarray,
               centre: np.ndarray, reach: np.ndarray, lo, spacing: float, kappa: float, e: float,
               vmin: np.ndarray, ssum: np.ndarray) -> None:
    """``polycc_lower_field`` on C-contiguous float64 arrays ``vmin``, ``ssum`` (in place)."""
    m = load()
    ffi, lib = m.ffi, m.lib
    assert vmin.flags.c_contiguous and ssum.flags.c_contiguous and vmin.dtype == ssum.dtype == np.float64
    arrs = [np.ascontiguousarray(a, t) for a, t in ((planes, np.float64), (first, np.int64), (count, np.int64),
                                                      (c, np.float64), (blocks, np.int64), (centre, np.float64),
                                                      (reach, np.float64), (np.asarray(lo), np.float64))]
    nx, ny, nz = vmin.shape
    lib.polycc_lower_field(_ptr(ffi, "const double *", arrs[0]), _ptr(ffi, "const int64_t *", arrs[1]),
                           _ptr(ffi, "const int64_t *", arrs[2]), _ptr(ffi, "const double *", arrs[3]),
                           _ptr(ffi, "const int64_t *", arrs[4]), _ptr(ffi, "const double *", arrs[5]),
                           _ptr(ffi, "const double *", arrs[6]), len(arrs[1]), _ptr(ffi, "const double *", arrs[7]),
                           float(spacing), nx, ny, nz, float(kappa), float(e), _ptr(ffi, "double *", vmin),
                           _ptr(ffi, "double *", ssum))
