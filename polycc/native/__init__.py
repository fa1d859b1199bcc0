"""Host-only C for the build's hot loops (cffi, float64), each the same method as a numpy reference it is tested
against, which runs instead (after a one-line notice) where no C compiler is available:

* :func:`cap_volumes` (``polycc_caps.c``): the drop volume (m^3) of every plane of a polytope at once, world
  frame, metres; reference :func:`polycc.geometry.halfplanes.drop_volumes`. The half-plane reduction
  (:mod:`polycc.budget.reduce`) asks for these about 100,000 times on a 6M-splat build, for polytopes of 5-128
  planes: a qhull half-space intersection per plane (scipy) spends 0.3-0.6 ms a call on setup alone, the numpy
  enumeration tens of array calls per polytope.
* :func:`count_inside` (``polycc_count.c``): occupied voxels entirely inside a convex polytope within an index
  box, lattice units; reference :meth:`polycc.cover.merge.VoxelBoxQuery.count_inside`, whose column
  arithmetic it repeats operation for operation. The cover's merge ranks about 160,000 candidate pairs by it on
  a 6M-splat build, 0.15 ms each in numpy, nearly all of it per-call overhead.

No library does either in one call, hence C. Built once per source hash into the build cache by
:func:`polycc.cbuild.build_cffi`.
"""

from __future__ import annotations

import sys
from functools import lru_cache
from pathlib import Path

import numpy as np

from polycc.cbuild import build_cffi
from polycc.errors import PolyccError
from polycc.geometry.halfplanes import drop_volumes, is_bounded

HERE = Path(__file__).resolve().parent
SOURCES = [HERE / "polycc_caps.c", HERE / "polycc_caps.h", HERE / "polycc_count.c", HERE / "polycc_count.h"]
CFLAGS = ["-O2", "-std=c99", "-ffp-contract=off", "-Wall", "-Wextra", "-Wconversion", "-Werror"]
MAX_PLANES = 128  # POLYCC_CAPS_MAX_PLANES: the C takes up to this many planes (the on-plane sets are 128-bit masks)
CDEF = """
int polycc_cap_volumes(const double *h, int m, double min_gamma, double *vol, int8_t *state);
int polycc_bounded_without(const double *n, int m, double min_gamma, int8_t *state);
int64_t polycc_count_inside(const uint8_t *dense, const int32_t *sat, const int64_t *keys, int64_t nkeys,
                            const int64_t *shape, const double *A, const double *b, int64_t F, const int64_t *lo,
                            const int64_t *hi, double tol, int64_t direct_cells);
"""


@lru_cache(maxsize=1)
def load():
    """Build (if needed) and import the extension; None (after a notice on stderr) if it cannot be built."""
    try:
        return build_cffi("_polycc_native", CDEF, '#include "polycc_caps.h"\n#include "polycc_count.h"\n', SOURCES,
                          [HERE], CFLAGS)
    except PolyccError as exc:
        print(f"polycc: the cover's voxel counts and the budget's drop volumes fall back to numpy (slower): {exc}",
              file=sys.stderr)
        return None


def _resolve(normals: np.ndarray, state: np.ndarray, min_gamma: float) -> np.ndarray:
    """Boundedness per row from the C's states, the rows too close to call decided by qhull."""
    ok = state == 1
    for j in np.flatnonzero(state < 0):
        ok[j] = is_bounded(np.delete(normals, j, axis=0), min_gamma)
    return ok


def bounded_without(normals: np.ndarray, min_gamma: float) -> np.ndarray | None:
    """:func:`polycc.geometry.halfplanes.bounded_without` in C; None if the C does not take these normals."""
    mod = load()
    n = np.ascontiguousarray(normals, np.float64)
    if mod is None or not 0 < len(n) <= MAX_PLANES:
        return None
    state = np.zeros(len(n), np.int8)
    ffi = mod.ffi
    if mod.lib.polycc_bounded_without(ffi.cast("const double *", ffi.from_buffer(n)), len(n), float(min_gamma),
                                      ffi.cast("int8_t *", ffi.from_buffer(state))) != 0:
        return None
    return _resolve(n, state, min_gamma)


def cap_volumes(h: np.ndarray, min_gamma: float, interior: np.ndarray | None = None,
                volume: float | None = None) -> np.ndarray:
    """:func:`polycc.geometry.halfplanes.drop_volumes` (same arguments, same result to ~1e-9 of the polytope's
    volume): in C up to :data:`MAX_PLANES` planes, the reference otherwise."""
    mod = load()
    h = np.ascontiguousarray(h, np.float64)
    m = len(h)
    if mod is not None and 0 < m <= MAX_PLANES:
        vol = np.zeros(m)
        state = np.zeros(m, np.int8)
        ffi = mod.ffi
        rc = mod.lib.polycc_cap_volumes(ffi.cast("const double *", ffi.from_buffer(h)), m, float(min_gamma),
                                        ffi.cast("double *", ffi.from_buffer(vol)),
                                        ffi.cast("int8_t *", ffi.from_buffer(state)))
        if rc == 0:
            return np.where(_resolve(h[:, :3], state, min_gamma), vol, np.inf)
    return drop_volumes(h, min_gamma, interior, volume)


def count_inside(dense: np.ndarray | None, sat: np.ndarray | None, keys: np.ndarray | None, shape, A: np.ndarray,
                 b: np.ndarray, lo, hi, tol: float, direct_cells: int) -> int | None:
    """``polycc_count_inside`` (see ``polycc_count.h``): ``dense`` bool and ``sat`` int32 C-contiguous grids, or
    ``keys`` (3, K) int64 sorted per axis; None if the C is not available."""
    mod = load()
    if mod is None:
        return None
    ffi, lib = mod.ffi, mod.lib
    A = np.ascontiguousarray(A, np.float64)
    b = np.ascontiguousarray(b, np.float64)
    box = np.array([*shape, *lo, *hi], np.int64)
    bp = ffi.cast("const int64_t *", ffi.from_buffer(box))
    null = ffi.NULL
    c = lib.polycc_count_inside(
        null if dense is None else ffi.cast("const uint8_t *", ffi.from_buffer(dense)),
        null if sat is None else ffi.cast("const int32_t *", ffi.from_buffer(sat)),
        null if keys is None else ffi.cast("const int64_t *", ffi.from_buffer(keys)),
        0 if keys is None else keys.shape[1], bp, ffi.cast("const double *", ffi.from_buffer(A)),
        ffi.cast("const double *", ffi.from_buffer(b)), len(A), bp + 3, bp + 6, float(tol), int(direct_cells))
    return None if c < 0 else int(c)
