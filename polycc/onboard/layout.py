"""The on-board scene layout (``firmware_app/src/polycc_scene_layout.h``, format 3), Python side.

:func:`pack_scene` turns polytopes, each an ``(H, 4)`` array of rows ``[nx, ny, nz, d]``
(outward unit normals, ``n . p <= d`` inside), plus optionally the vertices of each exact
polytope, into exactly the arrays the C kernel reads: a shared float32 normal table, 4-byte
quantized half-planes (uint16 normal index, int16 offset in quanta), 16-byte quantized
polytope records, 32-byte float32 cluster records and the scene constants.  Every stored
half-space is rounded OUTWARD so that it contains the exact polytope (``d_q >= max_v n_q . v``,
proved in float64 with an error bound).  :meth:`PackedScene.to_bytes` / :func:`scene_from_bytes`
give the flat image used by the bare-metal harness; the code generator emits the same numbers.
:func:`layout_bytes` predicts the flash bytes from the counts.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from fractions import Fraction
from functools import cached_property, lru_cache

import numpy as np

from polycc.errors import PolyccError
from polycc.geometry.halfplanes import chebyshev_centre, inv_gamma, is_bounded, polytope_vertices

SCENE_FORMAT = 3  # POLYCC_SCENE_FORMAT in polycc_scene_layout.h
NORMAL_BYTES = 12
PLANE_BYTES = 4
POLY_BYTES = 16
CLUSTER_BYTES = 32
ROOT_BYTES = 52  # polycc_scene_t on a 32-bit target: 8 words + 5 pointers (the last: the index, or NULL)
INDEX_BYTES = 56  # polycc_index_t: 5 floats, 4 uint16, 2 uint32, 5 pointers
MAX_POLY_PLANES = 256
MAX_PLANES = 65535
MAX_POLYS = 65535  # uint16 polytope index in the cluster records
MAX_NORMALS = 65536
LEAD_PLANES = 8
INV_GAMMA_UNIT = 2.0**-8
R_OUT_QUANTA = 16  # polytope r_out is stored in units of 16 quanta
QUANTUM_EXP_RANGE = (-20, 4)  # the kernel accepts quantum = 2^e for e in this range
DEFAULT_NORMAL_GRID = 4096
# Octant o of p - c: bit0 x < 0, bit1 y < 0, bit2 z < 0; s_o is the octant's diagonal.
OCTANT_SIGNS = np.array([[-1.0 if o & (1 << i) else 1.0 for i in range(3)] for o in range(8)])

NORMAL_DTYPE = np.dtype([("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
PLANE_DTYPE = np.dtype([("normal", "<u2"), ("d", "<i2")])
POLY_DTYPE = np.dtype([("c", "<i2", 3), ("r_out", "<u2"), ("r_in", "<u2"), ("inv_gamma", "<u2"), ("meta", "<u4")])
CLUSTER_DTYPE = np.dtype([("first", "<u2"), ("count", "<u2"), ("first_plane", "<u4"), ("cx", "<f4"), ("cy", "<f4"),
                          ("cz", "<f4"), ("r_out", "<f4"), ("inv_gamma", "<f4"), ("r_in", "<f4")])
# Decoded polytope records (what the kernel computes from POLY_DTYPE; exact float32 values).
DECODED_POLY_DTYPE = np.dtype([("first", "<u4"), ("count", "<u4"), ("cx", "<f4"), ("cy", "<f4"), ("cz", "<f4"),
                               ("r_out", "<f4"), ("inv_gamma", "<f4"), ("r_in", "<f4"), ("lead", "u1", 8)])
# format, n_clusters, n_polys, n_planes, n_normals, quantum, coord_bound, log_lmax
HEADER = struct.Struct("<IIIIIfff")
assert (NORMAL_DTYPE.itemsize, PLANE_DTYPE.itemsize, POLY_DTYPE.itemsize, CLUSTER_DTYPE.itemsize) == (
    NORMAL_BYTES, PLANE_BYTES, POLY_BYTES, CLUSTER_BYTES)
assert HEADER.size + 20 == ROOT_BYTES
# polycc_index_t without its pointers: origin, 1/s, cap D, dims, lists, entries
INDEX_HEADER = struct.Struct("<fffffHHHHII")
INDEX_DTYPE_FIELDS = ("ox", "oy", "oz", "inv_cell", "cap", "nx", "ny", "nz", "n_lists", "n_entries", "n_inner")
assert INDEX_HEADER.size + 20 == INDEX_BYTES

_UNIT_TOL = 1e-5  # |n| must be 1 within this before snapping
_U64 = 2.0**-53


def _pad4(n_u16: int) -> int:
    """Bytes of n uint16 values padded to a 4-byte boundary."""
    return 4 * ((2 * n_u16 + 3) // 4)


def index_bytes(n_cells: int, n_inner: int, n_lists: int, n_entries: int, n_polys: int) -> int:
    """Exact flash bytes of a spatial index (polycc_index_t and its five uint16 arrays, each padded
    to 4 bytes): ``56 + 2 n_cells + 16 n_inner + 2 (n_lists + 1) + 2 n_entries + 2 n_polys`` (+ padding)."""
    return INDEX_BYTES + _pad4(n_cells) + _pad4(8 * n_inner) + _pad4(n_lists + 1) + _pad4(n_entries) + _pad4(n_polys)


def layout_bytes(n_polys: int, n_planes: int, n_clusters: int, n_normals: int, index: int = 0) -> int:
    """Exact flash bytes of a format-3 scene (all generated arrays plus the root struct):
    ``52 + 4 n_planes + 16 n_polys + 32 n_clusters + 12 n_normals`` plus ``index`` (the bytes of the
    spatial index, :func:`index_bytes`, 0 without one).

    ``n_normals`` is the number of distinct stored normals (at most ``n_planes``; for covers with
    lattice normals it is small, see ``pack_scene(normal_grid=...)``); ``n_clusters`` is
    ``len(cluster_groups(n_polys, leaf))``, ``ceil(n_polys / leaf)`` to ``2 ceil(n_polys / leaf)``
    with ``leaf = max(4, ceil(sqrt(n_polys)))``: use :func:`n_clusters_for` for the exact count."""
    return ROOT_BYTES + PLANE_BYTES * n_planes + POLY_BYTES * n_polys + CLUSTER_BYTES * n_clusters + \
        NORMAL_BYTES * n_normals + index


def n_clusters_for(n_polys: int, leaf: int | None = None) -> int:
    """Number of clusters :func:`pack_scene` makes for ``n_polys`` polytopes (independent of
    the geometry: the median split only depends on the counts)."""
    if n_polys == 0:
        return 0
    leaf = leaf or max(4, math.ceil(math.sqrt(n_polys)))
    todo, groups = [n_polys], 0
    while todo:
        m = todo.pop()
        if m <= leaf:
            groups += 1
        else:
            todo += [m - m // 2, m // 2]
    return groups


@dataclass(frozen=True)
class SceneIndex:
    """The stored index (as the kernel reads it) plus build-time facts."""

    origin: np.ndarray  # float32 (3,)
    cell: float  # s, a power of two
    dims: tuple[int, int, int]
    cap: np.float32  # D
    cell_list: np.ndarray  # uint16 (n_cells,), node of cell i + nx (j + ny k): < n_lists a list id, else inner
    list_start: np.ndarray  # uint16 (n_lists + 1,)
    entries: np.ndarray  # uint16 polytope indices
    poly_first: np.ndarray  # uint16 (n_polys,), first plane of each polytope
    kappa: float | None = None  # the build kappa of the tightness slack (17 + log L) / kappa (not stored)
    children: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint16))  # uint16 (8 n_inner,)
    # build-time only (not stored): per non-empty leaf [list id, depth, polytopes, planes, expensive planes]
    work: np.ndarray | None = field(default=None, compare=False)

    @property
    def n_inner(self) -> int:
        return len(self.children) // 8

    def leaves(self) -> list[tuple[int, int]]:
        """(list id, depth) of every leaf reachable from a cell (depth 0: the cell itself)."""
        out, todo = set(), [(int(v), 0) for v in np.unique(self.cell_list)]
        seen = set()
        while todo:
            v, d = todo.pop()
            if v < self.n_lists:
                out.add((v, d))
            elif (v, d) not in seen:
                seen.add((v, d))
                b = v - self.n_lists
                todo += [(int(c), d + 1) for c in self.children[8 * b : 8 * b + 8]]
        return sorted(out)

    def lookup(self, cell: np.ndarray, t: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(list id, depth) for cells (>= 0) and the float32 cell coordinates t (3 arrays) the kernel
        computed: the descent of polycc_barrier (t doubled, exactly, per level; octant from the parity)."""
        v = self.cell_list.astype(np.int64)[cell]
        depth = np.zeros(len(cell), np.int64)
        s = [np.asarray(x, np.float32).copy() for x in t]
        nl = self.n_lists
        inner = v >= nl
        while inner.any():
            for a in s:
                a[inner] = a[inner] * np.float32(2.0)
            o = sum(((s[b][inner].astype(np.int64) & 1) << b) for b in range(3))
            v[inner] = self.children.astype(np.int64)[8 * (v[inner] - nl) + o]
            depth[inner] += 1
            inner = v >= nl
        return v, depth

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.dims))

    @property
    def n_lists(self) -> int:
        return len(self.list_start) - 1

    def nbytes(self) -> int:
        return index_bytes(self.n_cells, self.n_inner, self.n_lists, len(self.entries), len(self.poly_first))

    def lists(self) -> list[np.ndarray]:
        return [self.entries[int(a):int(b)] for a, b in zip(self.list_start[:-1], self.list_start[1:])]

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The five stored uint16 arrays, in image order."""
        return self.cell_list, self.children, self.list_start, self.entries, self.poly_first

    def list_work(self, counts: np.ndarray) -> np.ndarray:
        """(n_lists, 2): polytopes and half-planes of each list (``counts``: half-planes per polytope)."""
        counts = np.asarray(counts, np.int64)
        rows = [[len(x), int(counts[x.astype(np.int64)].sum())] for x in self.lists()]
        return np.array(rows, np.int64).reshape(-1, 2)

    def record(self) -> dict:
        """The values of the C struct polycc_index_t (without its pointers)."""
        return {"ox": np.float32(self.origin[0]), "oy": np.float32(self.origin[1]), "oz": np.float32(self.origin[2]),
                "inv_cell": np.float32(1.0 / self.cell), "cap": np.float32(self.cap), "nx": self.dims[0],
                "ny": self.dims[1], "nz": self.dims[2], "n_lists": self.n_lists, "n_entries": len(self.entries),
                "n_inner": self.n_inner}


@dataclass(frozen=True)
class PackedScene:
    """The arrays of one ``polycc_scene_t``, exactly as stored (raw) and as the C decodes them."""

    normals: np.ndarray  # NORMAL_DTYPE, (n_normals,)
    planes: np.ndarray  # PLANE_DTYPE, (n_planes,)
    polys_raw: np.ndarray  # POLY_DTYPE, (n_polys,)
    clusters: np.ndarray  # CLUSTER_DTYPE, (n_clusters,)
    quantum: np.float32
    coord_bound: np.float32
    log_lmax: np.float32
    order: np.ndarray | None = None  # order[i] = input index of packed polytope i
    index: SceneIndex | None = None  # spatial index (docs/barrier.md section 9), None: every polytope, no cap

    @property
    def n_polys(self) -> int:
        return int(self.polys_raw.shape[0])

    @property
    def n_planes(self) -> int:
        return int(self.planes.shape[0])

    @property
    def n_clusters(self) -> int:
        return int(self.clusters.shape[0])

    @property
    def n_normals(self) -> int:
        return int(self.normals.shape[0])

    @cached_property
    def polys(self) -> np.ndarray:
        """Decoded polytope records (DECODED_POLY_DTYPE): the exact float32 values the kernel
        computes, and each polytope's first plane."""
        return decode_polys(self.polys_raw, self.clusters, self.quantum)

    @cached_property
    def _plane_matrix(self) -> np.ndarray:
        nm = self.normals.view("<f4").reshape(-1, 3)
        out = np.empty((self.n_planes, 4), np.float32)
        out[:, :3] = nm[self.planes["normal"].astype(np.int64)] if self.n_planes else np.zeros((0, 3), np.float32)
        out[:, 3] = self.planes["d"].astype(np.float32) * np.float32(self.quantum)  # exact
        out.flags.writeable = False
        return out

    def plane_matrix(self) -> np.ndarray:
        """Decoded half-planes as an (n_planes, 4) float32 array [nx, ny, nz, d] (read-only);
        exactly the values the C computes (d = d_q * quantum is exact)."""
        return self._plane_matrix

    def polytopes(self) -> list[np.ndarray]:
        """Decode back to one (H_k, 4) float32 array per polytope, in packed order
        (``order`` maps packed positions to the input positions)."""
        m = self.plane_matrix()
        return [m[int(p["first"]) : int(p["first"]) + int(p["count"])].copy() for p in self.polys]

    def flash_bytes(self) -> int:
        """Bytes of the arrays plus the root struct on a 32-bit target (= layout_bytes)."""
        return layout_bytes(self.n_polys, self.n_planes, self.n_clusters, self.n_normals,
                            self.index.nbytes() if self.index is not None else 0)

    def with_index(self, index: SceneIndex | None) -> "PackedScene":
        """The same scene with this spatial index (None: without one)."""
        return PackedScene(self.normals, self.planes, self.polys_raw, self.clusters, self.quantum, self.coord_bound,
                           self.log_lmax, self.order, index)

    def bytes_per_plane(self) -> float:
        return self.flash_bytes() / max(1, self.n_planes)

    def to_bytes(self) -> bytes:
        """Flat image: header (format, counts, constants), clusters, polys, planes, normals, then, with
        an index, its header (INDEX_HEADER) and its uint16 arrays cell_list, list_start, entries,
        poly_first, each padded to 4 bytes with zeros."""
        head = HEADER.pack(SCENE_FORMAT, self.n_clusters, self.n_polys, self.n_planes, self.n_normals,
                           float(self.quantum), float(self.coord_bound), float(self.log_lmax))
        body = head + self.clusters.tobytes() + self.polys_raw.tobytes() + self.planes.tobytes() + \
            self.normals.tobytes()
        if self.index is None:
            return body
        ix = self.index
        r = ix.record()
        out = [body, INDEX_HEADER.pack(*(r[k] for k in INDEX_DTYPE_FIELDS))]
        for a in ix.arrays():
            b = np.asarray(a, "<u2").tobytes()
            out.append(b + bytes(-len(b) % 4))
        return b"".join(out)

    def without_polytopes(self) -> "PackedScene":
        """The same constants with no polytopes (an empty scene)."""
        return PackedScene(self.normals[:0], self.planes[:0], self.polys_raw[:0], self.clusters[:0], self.quantum,
                           self.coord_bound, self.log_lmax)

    def index_leaf(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(list id, depth) the kernel looks up for each state of p (n, 3) (float32 ops as in the C);
        list id -1 outside the grid box B (the kernel returns the cap D there)."""
        p = np.asarray(p, np.float32).reshape(-1, 3)
        r = self.index.record()
        with np.errstate(all="ignore"):
            t = [(p[:, i] - r[o]) * r["inv_cell"] for i, o in enumerate(("ox", "oy", "oz"))]
            inside = np.ones(len(p), bool)
            for ti, d in zip(t, ("nx", "ny", "nz")):
                inside &= (ti >= np.float32(0)) & (ti < np.float32(r[d]))
            ci = [np.where(inside, ti, 0).astype(np.int64) for ti in t]
        cell = ci[0] + r["nx"] * (ci[1] + r["ny"] * ci[2])
        out = np.full(len(p), -1, np.int64)
        depth = np.zeros(len(p), np.int64)
        w = np.nonzero(inside)[0]
        if len(w):
            out[w], depth[w] = self.index.lookup(cell[w], [ti[w] for ti in t])
        return out, depth


def decode_polys(raw: np.ndarray, clusters: np.ndarray, quantum) -> np.ndarray:
    """What the kernel reads from POLY_DTYPE records (exact conversions)."""
    q = np.float32(quantum)
    out = np.zeros(len(raw), DECODED_POLY_DTYPE)
    if len(raw) == 0:
        return out
    count = (raw["meta"] & 0xFF).astype(np.int64) + 1
    first = np.zeros(len(raw), np.int64)
    for C in clusters:
        a, n = int(C["first"]), int(C["count"])
        first[a : a + n] = int(C["first_plane"]) + np.r_[0, np.cumsum(count[a : a + n])[:-1]]
    out["first"], out["count"] = first, count
    c = raw["c"].astype(np.float32) * q
    out["cx"], out["cy"], out["cz"] = c[:, 0], c[:, 1], c[:, 2]
    out["r_out"] = raw["r_out"].astype(np.float32) * (q * np.float32(R_OUT_QUANTA))
    out["r_in"] = raw["r_in"].astype(np.float32) * q
    out["inv_gamma"] = raw["inv_gamma"].astype(np.float32) * np.float32(INV_GAMMA_UNIT)
    out["lead"] = np.stack([(raw["meta"] >> (8 + 3 * o)) & 7 for o in range(8)], axis=1)
    return out


def scene_from_bytes(blob: bytes) -> PackedScene:
    """Inverse of :meth:`PackedScene.to_bytes`."""
    fmt, n_clusters, n_polys, n_planes, n_normals, q, cb, ll = HEADER.unpack_from(blob, 0)
    if fmt != SCENE_FORMAT:
        raise PolyccError(f"scene image has format {fmt}, this polycc reads format {SCENE_FORMAT}; regenerate it")
    off = HEADER.size
    arrays = []
    for dt, n in ((CLUSTER_DTYPE, n_clusters), (POLY_DTYPE, n_polys), (PLANE_DTYPE, n_planes),
                  (NORMAL_DTYPE, n_normals)):
        arrays.append(np.frombuffer(blob, dt, n, off).copy())
        off += dt.itemsize * n
    clusters, polys, planes, normals = arrays
    index = None
    if len(blob) > off:
        r = dict(zip(INDEX_DTYPE_FIELDS, INDEX_HEADER.unpack_from(blob, off)))
        off += INDEX_HEADER.size
        arrs = []
        for m in (r["nx"] * r["ny"] * r["nz"], 8 * r["n_inner"], r["n_lists"] + 1, r["n_entries"], n_polys):
            arrs.append(np.frombuffer(blob, "<u2", m, off).copy())
            off += _pad4(m)
        index = SceneIndex(np.array([r["ox"], r["oy"], r["oz"]], np.float32), 1.0 / float(np.float32(r["inv_cell"])),
                           (r["nx"], r["ny"], r["nz"]), np.float32(r["cap"]), arrs[0], arrs[2], arrs[3], arrs[4],
                           children=arrs[1])
    return PackedScene(normals, planes, polys, clusters, np.float32(q), np.float32(cb), np.float32(ll), index=index)


def _f32_up(x: float) -> np.float32:
    """Smallest float32 >= x."""
    f = np.float32(x)
    return f if float(f) >= x else np.nextafter(f, np.float32(np.inf))


def _require_bounded(n: np.ndarray, k: int) -> None:
    if not is_bounded(n):
        raise PolyccError(f"polytope {k} is unbounded (its normals do not surround the origin); close it")


def _vertices(h: np.ndarray, k: int) -> np.ndarray:
    """Vertices of polytope k, after checking it is bounded and solid (PolyccError otherwise)."""
    _require_bounded(np.asarray(h)[:, :3], k)
    v = polytope_vertices(h)
    if v is None:
        raise PolyccError(f"polytope {k} is empty, flat or unbounded; every polytope needs a non-empty interior")
    return v


def _cluster_order(centres: np.ndarray, leaf: int) -> list[np.ndarray]:
    """Groups of at most ``leaf`` polytope indices: recursive median split on the widest axis."""
    groups, todo = [], [np.arange(len(centres))]
    while todo:
        idx = todo.pop()
        if len(idx) <= leaf:
            groups.append(idx)
            continue
        axis = int(np.argmax(np.ptp(centres[idx], axis=0)))
        srt = idx[np.argsort(centres[idx, axis], kind="stable")]
        todo += [srt[len(srt) // 2 :], srt[: len(srt) // 2]]
    return groups


def snap_normal(n: np.ndarray, grid: int | None) -> tuple[tuple, np.ndarray]:
    """(key, float32 normal with |n| <= 1 exactly).  With a grid K the direction is snapped to
    m / |m|, m = round(K n) an integer vector (lattice normals of voxel hulls map to the same
    entry); without, the float32 rounding of n is kept."""
    n = np.asarray(n, np.float64)
    if grid:
        key = _lattice_keys(n[None, :], grid)[0]
        return key, _lattice_normal(*key[1:]).copy()
    return _unit_f32(n / np.linalg.norm(n))


def snap_normals(n: np.ndarray, grid: int) -> tuple[list[tuple], np.ndarray]:
    """:func:`snap_normal` of every row of ``n`` (H, 3) with a grid K: (keys, (H, 3) float32), the same
    values, vectorised (a pack snaps every plane of every candidate; the exact check is made once per
    lattice direction)."""
    keys = _lattice_keys(np.asarray(n, np.float64), grid)
    f = np.array([_lattice_normal(*k[1:]) for k in keys], np.float32).reshape(-1, 3)
    return keys, f


def _lattice_keys(n: np.ndarray, grid: int) -> list[tuple]:
    """("m", m_x, m_y, m_z) per row: m = round(K n) divided by the gcd of its entries (1 if all 0)."""
    m = np.rint(n * grid).astype(np.int64)
    g = np.gcd.reduce(np.abs(m), axis=1)
    m //= np.where(g == 0, 1, g)[:, None]
    return [("m", a, b, c) for a, b, c in m.tolist()]


@lru_cache(maxsize=1 << 16)
def _lattice_normal(a: int, b: int, c: int) -> np.ndarray:
    """m / |m| for the integer direction m = (a, b, c), as :func:`_unit_f32` rounds it (read-only)."""
    m = np.array([a, b, c], np.int64)
    f = _unit_f32(m / math.sqrt(float(m @ m)))[1]
    f.flags.writeable = False
    return f


def _unit_f32(v: np.ndarray) -> tuple[tuple, np.ndarray]:
    """(("f", float32 bits), float32 v shrunk toward 0 until |f|^2 <= 1 exactly (rational check))."""
    f = v.astype(np.float32)
    while sum(Fraction(float(x)) ** 2 for x in f) > 1:
        i = int(np.argmax(np.abs(f)))
        f[i] = np.nextafter(f[i], np.float32(0))
    return ("f",) + tuple(int(b) for b in f.view(np.uint32)), f


def _outward_offsets(nq: np.ndarray, verts: np.ndarray, q: float) -> np.ndarray:
    """Smallest integers d_q with d_q * q >= max_v nq . v, proved.  The float64 dot products
    carry an error bound (|fl(a.b) - a.b| <= gamma_3 sum |a_i b_i|, gamma_3 < 3.01 u); a vertex
    whose bound straddles the candidate grid value is decided in exact rational arithmetic."""
    n64 = nq.astype(np.float64)
    prod = verts @ n64.T  # (V, H)
    bound = 4.0 * _U64 * (np.abs(verts) @ np.abs(n64.T))
    dq = np.ceil(np.max(prod, axis=0) / q)  # division by a power of two is exact
    for j in range(len(nq)):
        lim = dq[j] * q
        unsure = np.nonzero(prod[:, j] + bound[:, j] >= lim)[0]
        if len(unsure) == 0:
            continue
        nf = [Fraction(float(x)) for x in n64[j]]
        flim = Fraction(lim)
        if any(sum(nf[i] * Fraction(float(verts[v, i])) for i in range(3)) > flim for v in unsure):
            dq[j] += 1  # prod <= lim < true value <= prod + bound < lim + q
    return dq


def choose_quantum(vertices: list[np.ndarray]) -> float:
    """Smallest power-of-two quantum for which every stored coordinate fits an int16 (with a
    1/8 reserve for outward rounding and the centre): |v| / q <= 28672."""
    ext = max(float(np.max(np.linalg.norm(v, axis=1))) for v in vertices)
    e = math.ceil(math.log2(max(ext, 2.0**-30) / 28672.0))
    e = min(max(e, QUANTUM_EXP_RANGE[0]), QUANTUM_EXP_RANGE[1])
    return 2.0**e


def pack_scene(polytopes: list[np.ndarray], vertices: list[np.ndarray] | None = None, *, leaf: int | None = None,
               rel_safety: float = 1e-6, normal_grid: int | None = DEFAULT_NORMAL_GRID,
               quantum: float | None = None, merge_duplicates: bool = True,
               max_normals: int | None = None, record_cache: dict | None = None) -> PackedScene:
    """Pack polytopes ((H_k, 4) arrays [nx, ny, nz, d], unit outward normals) into format 3.

    ``vertices[k]`` ((V, 3) float64) are the vertices of the exact polytope k (every point to be
    covered lies in their convex hull); None computes them from the half-planes (qhull).  Each
    stored half-space is rounded outward so that it contains conv(vertices[k]): the normal is
    snapped to the shared table (``normal_grid`` K: direction m/|m|, m = round(K n); None keeps
    each float32 normal), then ``d_q = ceil(max_v n_q . v / q)`` proved in float64.  Half-planes
    that become identical are merged; the lead planes are moved first.  ``quantum`` (a power of
    two, metres) defaults to :func:`choose_quantum`.  ``merge_duplicates=False`` keeps planes
    whose snapped normals coincide (benchmarks that pad a scene with redundant planes).
    ``max_normals`` T caps the shared table: the normals are clustered on the sphere (the six
    axis directions always included, weighted spherical k-means) and every plane is snapped to
    its nearest table direction, its offset recomputed outward from the vertices; a polytope
    that snapping leaves unbounded gets its six axis-aligned tangent planes.  Then the flash
    size is ``layout_bytes(n_polys, n_planes, n_clusters, <= T)`` whatever the cover.  Polytopes are
    grouped into clusters of at most ``leaf`` (default max(4, ceil(sqrt(n)))) and stored cluster by cluster
    (``PackedScene.order``).  Culling bounds are computed in float64 from the decoded values and
    rounded outward (``rel_safety`` is a relative cushion for the float64 geometry).
    ``record_cache`` (a dict kept by the caller) memoises polytope records across packings.
    """
    rows, verts, q = _checked_inputs(polytopes, vertices, quantum)
    tvals, quant = _quantize(rows, verts, q, normal_grid, max_normals, merge_duplicates, record_cache)
    normals = np.zeros(len(tvals), NORMAL_DTYPE)
    normals.view("<f4").reshape(-1, 3)[:] = np.array(tvals, np.float32).reshape(-1, 3)
    recs = [_poly_record(k, *t, q, rel_safety, record_cache) for k, t in enumerate(quant)]
    return _assemble(normals, recs, q, leaf or max(4, math.ceil(math.sqrt(len(rows)))), rel_safety)


def _checked_inputs(polytopes, vertices, quantum) -> tuple[list[np.ndarray], list[np.ndarray], float]:
    """(half-plane rows, exact vertices, quantum) after checking every input."""
    if len(polytopes) == 0:
        raise PolyccError("no polytopes to pack; the scene needs at least one")
    if len(polytopes) > MAX_POLYS:
        raise PolyccError(f"{len(polytopes)} polytopes exceed the layout limit of {MAX_POLYS}; reduce the cover")
    rows = [np.asarray(h, dtype=np.float64).reshape(-1, 4) for h in polytopes]
    for k, h in enumerate(rows):
        _check_rows(k, h)
    if vertices is None:
        verts = [_vertices(h, k) for k, h in enumerate(rows)]
    else:
        if len(vertices) != len(rows):
            raise PolyccError(f"{len(vertices)} vertex sets for {len(rows)} polytopes")
        verts = [np.asarray(v, np.float64).reshape(-1, 3) for v in vertices]
        for k, v in enumerate(verts):
            if len(v) == 0 or not np.all(np.isfinite(v)):
                raise PolyccError(f"polytope {k} has no vertices or non-finite vertices")
    q = float(quantum) if quantum is not None else choose_quantum(verts)
    e = math.log2(q)
    if e != int(e) or not QUANTUM_EXP_RANGE[0] <= e <= QUANTUM_EXP_RANGE[1]:
        raise PolyccError(f"quantum {q} must be a power of two in [2^{QUANTUM_EXP_RANGE[0]}, 2^{QUANTUM_EXP_RANGE[1]}]")
    return rows, verts, q


def _quantize(rows, verts, q, normal_grid, max_normals, merge_duplicates, record_cache):
    """(table rows, per polytope (normal indices, d_q, normals)): every plane snapped to the shared
    table and its offset rounded outward over the exact vertices; unused table entries dropped."""
    table, tvals, per_poly = _normal_table(rows, normal_grid, max_normals)
    quant = []
    for k, (idx, v) in enumerate(zip(per_poly, verts)):
        if merge_duplicates:  # identical normals give identical planes: store one
            idx = list(dict.fromkeys(idx))
        nq = np.array([tvals[i] for i in idx], np.float32).reshape(-1, 3)
        if _needs_box(nq, record_cache):
            # snapping opened it, or its normals leave it too elongated for the record (1/gamma
            # over the uint16 field): add its axis-aligned bounding box, which contains it, so
            # the stored polytope still contains the exact one and 1/gamma <= sqrt(3)
            idx = list(dict.fromkeys(list(idx) + _axis_entries(table, tvals, normal_grid)))
            nq = np.array([tvals[i] for i in idx], np.float32)
        idx = np.array(idx, np.int64)
        dq = _outward_offsets(nq, v, q)
        if np.any(np.abs(dq) > 32767):
            raise PolyccError(f"polytope {k}: an offset does not fit int16 at quantum {q} m; pass a larger quantum")
        if len(idx) > MAX_POLY_PLANES:
            raise PolyccError(f"polytope {k} has {len(idx)} half-planes, the layout allows {MAX_POLY_PLANES}; split it")
        quant.append((idx, dq.astype(np.int64), nq))
    used = np.unique(np.concatenate([t[0] for t in quant]))  # drop unused table entries
    remap = np.full(len(tvals), -1, np.int64)
    remap[used] = np.arange(len(used))
    tvals = [tvals[i] for i in used]
    quant = [(remap[i], dq, nq) for i, dq, nq in quant]
    if len(tvals) > MAX_NORMALS:
        raise PolyccError(f"{len(tvals)} distinct normals exceed {MAX_NORMALS}; use a coarser normal_grid or "
                          "max_normals")
    total = sum(len(t[0]) for t in quant)
    if total > MAX_PLANES:
        raise PolyccError(f"{total} half-planes exceed the layout limit of {MAX_PLANES}; reduce the cover")
    return tvals, quant


def _assemble(normals: np.ndarray, recs: list[dict], q: float, leaf: int, rel_safety: float) -> PackedScene:
    """Group the polytope records into culling clusters and lay out the arrays, bounds outward."""
    centres = np.array([r["c64"] for r in recs])
    groups = _cluster_order(centres, leaf)
    order = np.concatenate(groups)
    planes = np.zeros(sum(len(r["idx"]) for r in recs), PLANE_DTYPE)
    polys = np.zeros(len(recs), POLY_DTYPE)
    clusters = np.zeros(len(groups), CLUSTER_DTYPE)
    first, pos, cb = 0, 0, 0.0
    for j, grp in enumerate(groups):
        cen = np.float32(centres[grp].mean(axis=0)).astype(np.float64)
        reach_out = reach_in = 0.0
        first0 = first
        for k in grp:
            r = recs[k]
            c, r_out, r_in = r["c64"], r["r_out"] * q * R_OUT_QUANTA, r["r_in"] * q
            dist = float(np.linalg.norm(c - cen))
            reach_out = max(reach_out, (dist + r_out) * (1 + rel_safety))
            reach_in = max(reach_in, (dist + r_in) * (1 + rel_safety))
            n = len(r["idx"])
            planes["normal"][first : first + n] = r["idx"]
            planes["d"][first : first + n] = r["dq"]
            polys[pos] = (r["cq"], r["r_out"], r["r_in"], r["inv_g"], r["meta"])
            cb = max(cb, float(np.max(np.abs(r["dq"]))) * q, float(np.sum(np.abs(c))) + r_out)
            first += n
            pos += 1
        inv_gc = max(recs[k]["inv_g"] for k in grp) * INV_GAMMA_UNIT
        clusters[j] = (pos - len(grp), len(grp), first0, cen[0], cen[1], cen[2], _f32_up(reach_out), inv_gc,
                       _f32_up(reach_in))
        cb = max(cb, float(np.sum(np.abs(cen))) + float(clusters[j]["r_out"]))
    lmax = max(len(r["idx"]) for r in recs)
    return PackedScene(normals, planes, polys, clusters, np.float32(q), _f32_up(cb * (1 + rel_safety)),
                       _f32_up(math.log(lmax) * (1 + rel_safety)), order)


_AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


def _normal_table(rows: list[np.ndarray], grid: int | None, max_normals: int | None):
    """(key -> index, float32 table rows, per-polytope lists of table indices)."""
    table: dict[tuple, int] = {}
    tvals: list[np.ndarray] = []
    if max_normals is not None:
        if max_normals < 6:
            raise PolyccError("max_normals must be at least 6 (the axis directions are always in the table)")
        for a in _AXES:  # indices 0..5: closing box planes
            key, f = snap_normal(a, grid)
            table[key] = len(tvals)
            tvals.append(f)
    per_poly = []
    if grid and rows:
        keys, fs = snap_normals(np.concatenate([h[:, :3] for h in rows]), grid)
        snapped = iter(zip(keys, fs))
    else:
        snapped = (snap_normal(n, grid) for h in rows for n in h[:, :3])
    for h in rows:
        idx = []
        for _ in range(len(h)):
            key, f = next(snapped)
            if key not in table:
                table[key] = len(tvals)
                tvals.append(f)
            idx.append(table[key])
        per_poly.append(idx)
    if max_normals is None or len(tvals) <= max_normals:
        return table, tvals, per_poly
    # weighted spherical k-means over the distinct normals, axes fixed as the first 6 centres
    X = np.array(tvals, np.float64)
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    w = np.bincount(np.concatenate([np.asarray(i) for i in per_poly]), minlength=len(X)).astype(np.float64)
    cent = [*_AXES]
    best = np.max(X @ np.array(cent).T, axis=1)
    while len(cent) < max_normals:  # farthest point (largest angle to the nearest centre), weighted
        j = int(np.argmax((1.0 - best) * np.sqrt(w + 1.0)))
        cent.append(X[j])
        best = np.maximum(best, X @ X[j])
    C = np.array(cent)
    for _ in range(12):
        lab = np.argmax(X @ C.T, axis=1)
        acc = np.zeros_like(C)
        np.add.at(acc, lab, X * w[:, None])
        nrm = np.linalg.norm(acc, axis=1)
        upd = nrm > 0
        upd[:6] = False
        C[upd] = acc[upd] / nrm[upd, None]
    lab = np.argmax(X @ C.T, axis=1)
    ctab = [snap_normal(c, None)[1] for c in C]
    return None, ctab, [[int(lab[i]) for i in idx] for idx in per_poly]


_MAX_INV_GAMMA = 0.5 * 65535 * INV_GAMMA_UNIT  # half the record's range: margin for the safety factors


def _needs_box(nq: np.ndarray, cache: dict | None) -> bool:
    """True if these normals bound no polytope or one too elongated for the record."""
    key = ("needs_box", nq.tobytes())
    if cache is not None and key in cache:
        return cache[key]
    n = nq.astype(np.float64)
    if not is_bounded(n):
        out = True
    else:
        try:
            out = inv_gamma(n) > _MAX_INV_GAMMA
        except PolyccError:
            out = True
    if cache is not None:
        cache[key] = out
    return out


def _axis_entries(table: dict | None, tvals: list, grid: int | None) -> list[int]:
    """Table indices of the six axis normals (entries 0..5 of a capped table; added to an
    uncapped one if missing)."""
    if table is None:
        return list(range(6))
    out = []
    for a in _AXES:
        key, f = snap_normal(a, grid)
        if key not in table:
            table[key] = len(tvals)
            tvals.append(f)
        out.append(table[key])
    return out


def _check_rows(k: int, h: np.ndarray) -> None:
    if len(h) == 0 or not np.all(np.isfinite(h)):
        raise PolyccError(f"polytope {k} has no half-planes or non-finite values")
    if len(h) > MAX_POLY_PLANES:
        raise PolyccError(f"polytope {k} has {len(h)} half-planes, the layout allows {MAX_POLY_PLANES}; split it")
    norms = np.linalg.norm(h[:, :3], axis=1)
    if np.any(np.abs(norms - 1.0) > _UNIT_TOL):
        raise PolyccError(f"polytope {k} has normals that are not unit length; normalise [nx, ny, nz, d] rows")


def _poly_record(k: int, idx: np.ndarray, dq: np.ndarray, nq: np.ndarray, q: float, rel_safety: float,
                 cache: dict | None = None) -> dict:
    """Quantized record of one polytope: lead planes first, centre on the grid, bounds outward.
    The record depends only on the decoded planes (nq, dq), q and rel_safety, so ``cache`` may
    memoise it across packings that share polytopes (candidates of one build)."""
    if cache is None:
        return _poly_record_geometry(k, idx, dq, nq, q, rel_safety)
    key = (nq.tobytes(), np.asarray(dq, np.int64).tobytes(), q, rel_safety)
    if key not in cache:
        rec = _poly_record_geometry(k, np.arange(len(idx)), dq, nq, q, rel_safety)
        cache[key] = rec
    rec = dict(cache[key])
    rec["idx"] = np.asarray(idx)[rec["idx"]]  # the cached idx is the lead-first permutation
    return rec


def _poly_record_geometry(k: int, idx: np.ndarray, dq: np.ndarray, nq: np.ndarray, q: float, rel_safety: float) -> dict:
    n = nq.astype(np.float64)
    d = dq.astype(np.float64) * q  # exact decoded offsets
    _require_bounded(n, k)
    lead = np.argmax(OCTANT_SIGNS @ n.T, axis=1)
    firsts = list(dict.fromkeys(int(x) for x in lead))  # distinct lead planes, <= 8
    perm = np.array(firsts + [i for i in range(len(idx)) if i not in firsts], np.int64)
    idx, dq, n, d = idx[perm], dq[perm], n[perm], d[perm]
    lead_new = [firsts.index(int(x)) for x in lead]
    c64, _ = chebyshev_centre(np.c_[n, d])
    cq = np.rint(c64 / q)
    c = cq * q
    slack = d - n @ c
    if np.min(slack) <= 1e-12 * (1 + np.max(np.abs(d))) or np.any(np.abs(cq) > 32767):
        raise PolyccError(f"polytope {k} is too thin to hold an interior point on the {q} m grid; drop or thicken it")
    inv_g = inv_gamma(n) * (1 + rel_safety)
    r_out = float(np.max(slack)) * inv_g * (1 + rel_safety)
    r_in = float(np.min(slack)) * (1 - rel_safety)
    inv_gq = math.ceil(inv_g / INV_GAMMA_UNIT)
    r_outq = math.ceil(r_out / (q * R_OUT_QUANTA))
    if inv_gq > 65535 or r_outq > 65535:
        raise PolyccError(f"polytope {k} is too elongated for the record (1/gamma {inv_g:.3g}, R {r_out:.3g} m)")
    leads24 = sum(int(l) << (3 * o) for o, l in enumerate(lead_new))
    return {"idx": idx, "dq": dq, "cq": cq.astype(np.int64), "c64": c, "r_out": r_outq,
            "r_in": min(65535, max(0, math.floor(r_in / q))), "inv_g": inv_gq, "meta": (len(idx) - 1) | (leads24 << 8)}


def stored_vertices(packed: PackedScene) -> list[np.ndarray | None]:
    """Vertices (float64, metres) of each stored polytope as the C decodes it, in packed order;
    None where qhull cannot enumerate them (drawing only)."""
    out = []
    for k, h in enumerate(packed.polytopes()):
        p = packed.polys[k]
        out.append(polytope_vertices(h.astype(np.float64), np.array([p["cx"], p["cy"], p["cz"]], np.float64)))
    return out
