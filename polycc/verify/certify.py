"""Independent certification of a cover family (``polycc verify``).

This module shares no code with the cover pipeline: it reads ``cover.npz`` with
``numpy.load`` itself, replays the merge list itself and has its own point-in-polytope
test. Inputs are the occupied voxels and the kept ellipsoids, which the caller derives
from the scene again.

Checks (every tolerance counts *against* the cover: a point is inside a polytope only if
``n . p <= d`` holds in float64 for every row, with no slack):

(a) Every occupied voxel lies inside one polytope: all 8 corners, computed as
    ``origin + (i + {0,1}) * g``, satisfy one polytope's half-planes.
    - Directly, corner by corner, at the listed levels n.
    - At *every* level n = N..1 by a certificate: after each merge (a, b) -> c the voxels
      that a and b held must lie in c. We keep, per polytope, the extreme points (qhull
      vertices) of the corners of the voxels it holds; c holds them iff it contains
      those points (c is convex). A voxel that c does not hold is searched for in every
      live polytope; if none holds it the level fails.
(b) Every kept ellipsoid is covered: points on the surface and inside each ellipsoid
    (at least ``per_ellipsoid`` each and ``min_total`` in total) are each inside some
    polytope of H^n, at the listed levels.
(c) Conservativeness ``Vol(U H^n) / Vol(V+)`` by Monte Carlo with a 95% confidence
    interval: for each polytope i, points uniform in its bounding box B_i count
    ``1[x in H_i] / #{j : x in H_j}``; the sum over i of ``Vol(B_i) * mean_i`` is an
    unbiased estimate of the union's volume (each point of the union is counted once).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

FORMAT = "polycc-cover-family/1"
CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
MAX_FULL_RECHECKS = 20  # after this many failing levels, later ones are flagged without a full recount


@dataclass
class FamilyArrays:
    """The parts of cover.npz the checks need, read independently of the cover code."""

    g: float
    origin: np.ndarray
    grid_indices: np.ndarray
    merges: np.ndarray
    plane_ptr: np.ndarray
    planes: np.ndarray
    vertex_ptr: np.ndarray
    vertices: np.ndarray
    meta: dict
    leaves: int = -1  # number of leaf polytopes when there is no merge list (stored build output)

    @staticmethod
    def from_family(fam) -> "FamilyArrays":
        """From any object with a cover family's attributes (e.g. an in-memory CoverFamily),
        for measurements; certification reads the file with :func:`read_family`."""
        return FamilyArrays(float(fam.voxel_size), np.asarray(fam.origin, np.float64), fam.grid_indices, fam.merges,
                            fam.plane_ptr, fam.planes, fam.vertex_ptr, fam.vertices, dict(fam.meta))

    @property
    def n_leaves(self) -> int:
        return self.leaves if self.leaves >= 0 else len(self.merges) + 1

    def live_after(self, steps: int) -> np.ndarray:
        """Node ids alive after the first ``steps`` merges."""
        N = self.n_leaves
        dead = np.zeros(N + steps, bool)
        dead[self.merges[:steps].reshape(-1)] = True
        return np.flatnonzero(~dead)


def read_stored(path: str | Path, g: float, origin: np.ndarray) -> FamilyArrays:
    """The polytopes of a `polycc build` folder exactly as the C decodes them (manifest.json),
    as a family of n leaves with no merges. Vertices (only used to pick candidate polytopes
    for a point; a wrong one can only make a check fail) come from qhull here."""
    from scipy.optimize import linprog
    from scipy.spatial import HalfspaceIntersection

    path = Path(path)
    man = json.loads((path / "manifest.json" if path.is_dir() else path).read_text())
    if man.get("format") != "polycc-scene/1":
        raise ValueError(f"{path}: manifest format {man.get('format')!r}, expected 'polycc-scene/1'")
    planes, verts, pp, vp = [], [], [0], [0]
    for k, item in enumerate(man["polytopes"]):
        h = np.asarray(item["halfplanes"], np.float64).reshape(-1, 4)
        nrm = np.linalg.norm(h[:, :3], axis=1)
        res = linprog(c=[0, 0, 0, -1], A_ub=np.c_[h[:, :3], nrm], b_ub=h[:, 3], bounds=[(None, None)] * 3 + [(0, None)],
                      method="highs")
        if res.status != 0 or res.x[3] <= 0:
            raise ValueError(f"{path}: stored polytope {k} is empty or unbounded")
        v = HalfspaceIntersection(np.c_[h[:, :3], -h[:, 3]], res.x[:3]).intersections
        planes.append(h)
        verts.append(v)
        pp.append(pp[-1] + len(h))
        vp.append(vp[-1] + len(v))
    return FamilyArrays(g=float(g), origin=np.asarray(origin, np.float64), grid_indices=np.empty((0, 3), np.int64),
                        merges=np.empty((0, 2), np.int64), plane_ptr=np.array(pp), planes=np.concatenate(planes),
                        vertex_ptr=np.array(vp), vertices=np.concatenate(verts), meta=man.get("stats", {}),
                        leaves=len(planes))


def read_family(path: str | Path) -> FamilyArrays:
    path = Path(path)
    if path.is_dir():
        path = path / "cover.npz"
    with np.load(path, allow_pickle=False) as z:
        if str(z["format"]) != FORMAT:
            raise ValueError(f"{path}: format {z['format']!s}, expected {FORMAT}")
        return FamilyArrays(
            g=float(z["voxel_size"]), origin=z["origin"].astype(np.float64), grid_indices=z["grid_indices"],
            merges=z["merges"].astype(np.int64), plane_ptr=z["plane_ptr"], planes=z["planes"].astype(np.float64),
            vertex_ptr=z["vertex_ptr"], vertices=z["vertices"], meta=json.loads(str(z["meta"])),
        )


class PolytopeSet:
    """A set of polytopes with a uniform-grid index for point queries."""

    def __init__(self, fam: FamilyArrays, nodes: np.ndarray):
        self.nodes = np.asarray(nodes, np.int64)
        self.planes = [fam.planes[fam.plane_ptr[nd] : fam.plane_ptr[nd + 1]] for nd in self.nodes]
        # Boxes from the stored vertices, widened: they only choose which polytopes to try,
        # so a wrong box can make a check fail, never pass.
        lo = np.empty((len(self.nodes), 3))
        hi = np.empty((len(self.nodes), 3))
        for k, nd in enumerate(self.nodes):
            v = fam.vertices[fam.vertex_ptr[nd] : fam.vertex_ptr[nd + 1]]
            lo[k], hi[k] = v.min(axis=0), v.max(axis=0)
        pad = 1e-6 + 1e-3 * fam.g
        self.lo, self.hi = lo - pad, hi + pad
        ext = np.median(self.hi - self.lo, axis=0).max()
        self.cell = max(float(ext), 4 * fam.g)
        self.base = self.lo.min(axis=0)
        clo = np.floor((self.lo - self.base) / self.cell).astype(np.int64)
        chi = np.floor((self.hi - self.base) / self.cell).astype(np.int64)
        self.dims = chi.max(axis=0) + 1
        n_cells = np.prod(chi - clo + 1, axis=1)
        owner = np.repeat(np.arange(len(self.nodes)), n_cells)
        j = np.arange(n_cells.sum()) - np.repeat(np.cumsum(n_cells) - n_cells, n_cells)
        ext3 = (chi - clo + 1)[owner]
        c = clo[owner] + np.stack([j % ext3[:, 0], (j // ext3[:, 0]) % ext3[:, 1], j // (ext3[:, 0] * ext3[:, 1])], 1)
        key = self._key(c)
        order = np.argsort(key, kind="stable")
        self.cell_keys, self.cell_owner = key[order], owner[order]

    def _key(self, c: np.ndarray) -> np.ndarray:
        return (c[:, 0] * self.dims[1] + c[:, 1]) * self.dims[2] + c[:, 2]

    def candidates(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (point row, polytope row) whose widened box holds the point."""
        c = np.floor((p - self.base) / self.cell).astype(np.int64)
        ok = np.all((c >= 0) & (c < self.dims), axis=1)
        key = np.where(ok, self._key(np.clip(c, 0, self.dims - 1)), -1)
        a = np.searchsorted(self.cell_keys, key, "left")
        b = np.searchsorted(self.cell_keys, key, "right")
        cnt = np.where(ok, b - a, 0)
        pi = np.repeat(np.arange(len(p)), cnt)
        j = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        qi = self.cell_owner[np.repeat(a, cnt) + j]
        inb = np.all((p[pi] >= self.lo[qi]) & (p[pi] <= self.hi[qi]), axis=1)
        return pi[inb], qi[inb]

    def inside_pairs(self, pts: np.ndarray, pi: np.ndarray, qi: np.ndarray) -> np.ndarray:
        """Bool per pair: point pts[pi] satisfies every half-plane of polytope qi (grouped by polytope)."""
        out = np.empty(len(pi), bool)
        if len(pi) == 0:
            return out
        order = np.argsort(qi, kind="stable")
        q_sorted = qi[order]
        cut = np.flatnonzero(np.diff(q_sorted)) + 1
        for a, b in zip(np.concatenate([[0], cut]), np.concatenate([cut, [len(order)]])):
            H = self.planes[q_sorted[a]]
            sel = order[a:b]
            out[sel] = np.all(pts[pi[sel]] @ H[:, :3].T <= H[:, 3], axis=1)
        return out

    def count_containing(self, pts: np.ndarray) -> np.ndarray:
        """Number of polytopes containing each point."""
        out = np.zeros(len(pts), np.int64)
        for s in range(0, len(pts), 100_000):
            p = pts[s : s + 100_000]
            pi, qi = self.candidates(p)
            ins = self.inside_pairs(p, pi, qi)
            out[s : s + 100_000] = np.bincount(pi[ins], minlength=len(p))
        return out

    def voxel_witness(self, corners: np.ndarray) -> np.ndarray:
        """For voxels given by (V, 8, 3) corners: the row of a polytope holding all 8, or -1."""
        V = len(corners)
        wit = np.full(V, -1, np.int64)
        step = 50_000
        for s in range(0, V, step):
            cor = corners[s : s + step]
            pi, qi = self.candidates(cor[:, 0])  # a holding polytope's box holds corner 0
            ok = np.ones(len(pi), bool)
            for c in range(8):
                idx = np.flatnonzero(ok)
                ok[idx] = self.inside_pairs(cor[:, c], pi[idx], qi[idx])
            wit[s + pi[ok]] = qi[ok]
        return wit


def _voxel_keys(idx: np.ndarray) -> np.ndarray:
    i = idx.astype(np.int64) + (1 << 20)
    return (i[:, 0] << 42) | (i[:, 1] << 21) | i[:, 2]


def voxel_corners(indices: np.ndarray, g: float, origin: np.ndarray) -> np.ndarray:
    """(V, 8, 3) float64 world corners ``origin + (i + {0,1}^3) * g``."""
    return origin + (indices[:, None, :].astype(np.float64) + CORNERS[None]) * g


def sample_ellipsoids(centers, axes, per: int, rng: np.random.Generator) -> np.ndarray:
    """``per`` points per ellipsoid {c + L u : |u| <= 1}: the 6 axis tips, then half on
    the surface (|u| = 1) and half inside (radius U^(1/3)). Returns (E * per, 3)."""
    E = len(centers)
    tips = np.concatenate([np.eye(3), -np.eye(3)])
    u = rng.normal(size=(E, per, 3))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    r = np.ones((E, per))
    r[:, per // 2 :] = rng.random((E, per - per // 2)) ** (1 / 3)
    u *= r[:, :, None]
    u[:, : min(6, per)] = tips[: min(6, per)]
    return (centers[:, None, :] + np.einsum("eij,epj->epi", axes, u)).reshape(-1, 3)


def union_volume_mc(ps: PolytopeSet, samples: int, rng: np.random.Generator) -> tuple[float, float]:
    """(estimate, 95% half-width) of the volume of the union of ``ps``, m^3."""
    vol_box = np.prod(ps.hi - ps.lo, axis=1)
    m = np.maximum(8, np.round(samples * vol_box / vol_box.sum()).astype(np.int64))
    owner = np.repeat(np.arange(len(vol_box)), m)
    x = ps.lo[owner] + rng.random((len(owner), 3)) * (ps.hi - ps.lo)[owner]
    mine = ps.inside_pairs(x, np.arange(len(x)), owner)
    cnt = np.zeros(len(x), np.int64)
    cnt[mine] = ps.count_containing(x[mine])
    f = np.zeros(len(x))
    f[mine] = 1.0 / np.maximum(cnt[mine], 1)
    s1 = np.bincount(owner, weights=f, minlength=len(m))
    s2 = np.bincount(owner, weights=f * f, minlength=len(m))
    mean = s1 / m
    var = np.maximum(s2 / m - mean**2, 0) / np.maximum(m - 1, 1)
    return float((vol_box * mean).sum()), float(1.96 * np.sqrt((vol_box**2 * var).sum()))


@dataclass
class LevelReport:
    n: int
    voxels_checked: int
    voxels_uncovered: int
    points_sampled: int = 0
    points_uncovered: int = 0
    conservativeness: float = float("nan")
    conservativeness_ci: float = float("nan")
    halfplanes: int = 0


@dataclass
class VerifyReport:
    levels: list = field(default_factory=list)
    certificate_levels: int = 0
    certificate_failures: list = field(default_factory=list)
    voxels: int = 0
    grid_matches_cover: bool = True
    stored: bool = False  # a build folder's stored polytopes (else a cover family)
    occupancy: str = "exact"  # "exact", or "filtered" (floater filter: certified against the filtered V+)
    floater_filter: dict | None = None

    @property
    def ok(self) -> bool:
        return not self.certificate_failures and all(
            lv.voxels_uncovered == 0 and lv.points_uncovered == 0 for lv in self.levels)

    def as_dict(self) -> dict:
        return {"ok": self.ok, "voxels": self.voxels, "grid_matches_cover": self.grid_matches_cover,
                "occupancy": self.occupancy, "floater_filter": self.floater_filter,
                "certificate_levels": self.certificate_levels, "certificate_failures": self.certificate_failures[:20],
                "levels": [l.__dict__ for l in self.levels]}


def _extreme_points(pts: np.ndarray) -> np.ndarray:
    if len(pts) <= 8:
        return pts
    try:
        return pts[ConvexHull(pts).vertices]
    except Exception:  # flat or tiny sets: keep them all
        return pts


def certify_all_levels(fam: FamilyArrays, indices: np.ndarray, progress=None) -> list:
    """Check (a) at every level by the certificate described in the module docstring.

    Returns the list of (n, uncovered voxel count) for the failing levels (empty = pass).
    """
    N = fam.n_leaves
    ps = PolytopeSet(fam, fam.live_after(0))
    corners = voxel_corners(indices, fam.g, fam.origin)
    wit = ps.voxel_witness(corners)
    failures = []
    if np.any(wit < 0):
        failures.append((N, int(np.count_nonzero(wit < 0))))
    node_of = np.where(wit >= 0, ps.nodes[np.maximum(wit, 0)], -1)
    order = np.argsort(node_of, kind="stable")
    bounds = np.searchsorted(node_of[order], np.arange(N + 1))
    held: dict = {}
    for k in range(N):
        v = order[bounds[k] : bounds[k + 1]]
        held[k] = _extreme_points(corners[v].reshape(-1, 3)) if len(v) else np.empty((0, 3))
    H = {}

    def planes(nd):
        if nd not in H:
            H[nd] = fam.planes[fam.plane_ptr[nd] : fam.plane_ptr[nd + 1]]
        return H[nd]

    for t, (a, b) in enumerate(fam.merges):
        c = N + t
        pts = np.concatenate([held.pop(int(a)), held.pop(int(b))])
        P = planes(c)
        inside = np.all(pts @ P[:, :3].T <= P[:, 3], axis=1) if len(pts) else np.ones(0, bool)
        if not np.all(inside) and len(failures) >= MAX_FULL_RECHECKS:
            failures.append((N - t - 1, -1))  # -1: at least one; not recounted, the cover is known broken
        elif not np.all(inside):
            # c lost something; are the corners in some other live polytope? (full check)
            live = fam.live_after(t + 1)
            sub = PolytopeSet(fam, live)
            w = sub.voxel_witness(corners)
            bad = int(np.count_nonzero(w < 0))
            if bad:
                failures.append((N - t - 1, bad))
        held[c] = _extreme_points(pts)
        if progress is not None and t % 512 == 0:
            progress(t + 1)
    return failures


def check_level(fam: FamilyArrays, n: int, indices: np.ndarray, centers=None, axes=None, per_ellipsoid: int = 64,
                min_total: int = 1_000_000, mc_samples: int = 200_000, rng=None) -> LevelReport:
    """Direct checks (a), (b), (c) at level n."""
    rng = np.random.default_rng(0) if rng is None else rng
    nodes = fam.live_after(fam.n_leaves - n)
    ps = PolytopeSet(fam, nodes)
    wit = ps.voxel_witness(voxel_corners(indices, fam.g, fam.origin))
    rep = LevelReport(n=n, voxels_checked=len(indices), voxels_uncovered=int(np.count_nonzero(wit < 0)))
    rep.halfplanes = int((fam.plane_ptr[nodes + 1] - fam.plane_ptr[nodes]).sum())
    if centers is not None and len(centers):
        per = max(per_ellipsoid, int(np.ceil(min_total / len(centers))))
        step = max(1, 2_000_000 // per)
        keys = _voxel_keys(indices)
        order = np.argsort(keys)
        skeys = keys[order]
        for s in range(0, len(centers), step):
            pts = sample_ellipsoids(centers[s : s + step], axes[s : s + step], per, rng)
            rep.points_sampled += len(pts)
            # first try the polytope that holds the point's voxel, then search all candidates
            vk = _voxel_keys(np.floor((pts - fam.origin) / fam.g).astype(np.int64))
            pos = np.minimum(np.searchsorted(skeys, vk), len(skeys) - 1)
            w = np.where(skeys[pos] == vk, wit[order[pos]], -1)
            ok = np.zeros(len(pts), bool)
            has = np.flatnonzero(w >= 0)
            ok[has] = ps.inside_pairs(pts, has, w[has])
            rest = np.flatnonzero(~ok)
            rep.points_uncovered += int(np.count_nonzero(ps.count_containing(pts[rest]) == 0))
    if mc_samples > 0:
        vol, ci = union_volume_mc(ps, mc_samples, rng)
        occ = len(indices) * fam.g**3
        rep.conservativeness, rep.conservativeness_ci = vol / occ, ci / occ
    return rep


def default_levels(N: int) -> list[int]:
    return sorted({n for n in (1, 10, 30, 50, 100, 150, N) if 1 <= n <= N}, reverse=True)
