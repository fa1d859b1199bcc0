"""The merge-family file: every polytope cover H^n, n = N..1, of one occupancy grid.

File ``cover.npz`` (``np.load(..., allow_pickle=False)``), format ``polycc-cover-family/1``.
Node ids: ``0..N-1`` are the sub-cover clusters (leaves); merge step ``t`` (0-based)
joins nodes ``merges[t] = (a, b)`` into node ``N + t``. H^n is the set of nodes alive
after the first ``N - n`` merges. Keys:

=================  ==================  ===================================================
key                shape / dtype       meaning
=================  ==================  ===================================================
format             str                 ``polycc-cover-family/1``
voxel_size         float64             g, metres
origin             (3,) float64        voxel ``i`` spans ``[origin + i g, origin + (i+1) g]``
grid_indices       (V, 3) int64        occupied voxels V+ the cover was built from
leaf_voxel         (N,) int64          row of ``grid_indices`` at the centre of each leaf
leaf_ptr           (N+1,) int64        CSR pointers into ``leaf_members``
leaf_members       (L,) int64          rows of ``grid_indices`` in each leaf cluster C_v
merges             (N-1, 2) int64      node ids merged at each step
merge_costs        (N-1,) float64      cost of each merge, m^3
node_weight        (2N-1,) float64     W of each node (Eq. 11, see merge.py), m^3
node_volume        (2N-1,) float64     Vol(Hull) of each node, m^3
plane_ptr          (2N,) int64         CSR pointers into ``planes``
planes             (P, 4) float64      rows ``[nx, ny, nz, d]``: ``n . p <= d``, ``|n| = 1``
vertex_ptr         (2N,) int64         CSR pointers into ``vertices``
vertices           (Q, 3) float64      hull vertices, metres
meta               str (JSON)          options, scene sha256, timings, statistics
=================  ==================  ===================================================

Every polytope's planes are final (outward-rounded, coplanar facets merged): materialising
H^n is indexing only, no geometry is recomputed.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError

FORMAT = "polycc-cover-family/1"
FILENAME = "cover.npz"


@dataclass
class Polytope:
    """One convex polytope: ``halfplanes`` (H, 4) ``[nx, ny, nz, d]`` (``n . p <= d``,
    unit ``n``), ``vertices`` (V, 3) metres, ``node`` id in the family, ``volume`` m^3."""

    halfplanes: np.ndarray
    vertices: np.ndarray
    node: int
    volume: float

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Bool per point (M, 3): inside or on the boundary."""
        return np.all(p @ self.halfplanes[:, :3].T <= self.halfplanes[:, 3], axis=1)


@dataclass
class CoverFamily:
    voxel_size: float
    origin: np.ndarray
    grid_indices: np.ndarray
    leaf_voxel: np.ndarray
    leaf_ptr: np.ndarray
    leaf_members: np.ndarray
    merges: np.ndarray
    merge_costs: np.ndarray
    node_weight: np.ndarray
    node_volume: np.ndarray
    plane_ptr: np.ndarray
    planes: np.ndarray
    vertex_ptr: np.ndarray
    vertices: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def n_max(self) -> int:
        """N, the size of the sub-cover (the largest materialisable n)."""
        return int(len(self.leaf_voxel))

    def active_nodes(self, n: int) -> np.ndarray:
        """Sorted node ids of H^n (1 <= n <= N)."""
        N = self.n_max
        if not 1 <= n <= N:
            raise PolyccError(f"n = {n}: this cover family holds n = 1..{N}; pick n in that range")
        steps = N - n
        alive = np.ones(N + steps, bool)
        alive[self.merges[:steps].ravel()] = False
        return np.flatnonzero(alive)

    def polytope(self, node: int) -> Polytope:
        a, b = self.plane_ptr[node], self.plane_ptr[node + 1]
        c, d = self.vertex_ptr[node], self.vertex_ptr[node + 1]
        return Polytope(self.planes[a:b], self.vertices[c:d], int(node), float(self.node_volume[node]))

    def materialise(self, n: int) -> list[Polytope]:
        """H^n as a list of n polytopes (half-planes + vertices)."""
        return [self.polytope(int(k)) for k in self.active_nodes(n)]

    def halfplane_count(self, n: int) -> int:
        k = self.active_nodes(n)
        return int((self.plane_ptr[k + 1] - self.plane_ptr[k]).sum())

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        if path.is_dir() or path.suffix != ".npz":
            path = path / FILENAME
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"format": np.array(FORMAT), "meta": np.array(json.dumps(self.meta, sort_keys=True)),
                  **{k: getattr(self, k) for k in _ARRAY_KEYS}}
        # np.savez_compressed's own layout (one .npy per array in a deflated zip), at zlib level 1: it has no
        # level argument, and its default 6 took 1.5 s of a 2.5 cm build's serial path for 20 % fewer bytes
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
            for k, a in arrays.items():
                with z.open(k + ".npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)
        return path

    @staticmethod
    def load(path: str | Path) -> "CoverFamily":
        path = Path(path)
        if path.is_dir():
            path = path / FILENAME
        try:
            with np.load(path, allow_pickle=False) as z:
                if "format" not in z or str(z["format"]) != FORMAT:
                    raise PolyccError(f"{path}: not a polycc cover family; make one with `polycc cover SCENE -o DIR`")
                kw = {k: z[k] for k in _ARRAY_KEYS}
                meta = json.loads(str(z["meta"]))
        except FileNotFoundError:
            raise PolyccError(f"{path}: no such file; make it with `polycc cover SCENE -o {path.parent}`") from None
        except (OSError, ValueError, KeyError) as exc:
            raise PolyccError(f"{path}: cannot read cover family ({exc}); re-create it with `polycc cover`") from None
        kw["voxel_size"] = float(kw["voxel_size"])
        return CoverFamily(meta=meta, **kw)


_ARRAY_KEYS = (
    "voxel_size", "origin", "grid_indices", "leaf_voxel", "leaf_ptr", "leaf_members", "merges",
    "merge_costs", "node_weight", "node_volume", "plane_ptr", "planes", "vertex_ptr", "vertices",
)
