"""Tiled, hierarchical PolyMerge: the cover of a large V+ as a graph of tasks on every core.

Data flow (every task a pure function of its arguments; :mod:`polycc.parallel` runs the graph
in this process, on local worker processes or on Dask, with the same result):

1. **Tiles.** V+ is cut by a kd-tree on voxel counts (median split along the longest axis of
   each region's bounding box) into tiles of at most ``tile_voxels`` voxels. The cuts depend
   only on V+, never on the number of workers.
2. **Tile task** (one per tile, in parallel): clusters C_v of the tile's voxels only (a cluster
   never crosses a seam, so its weight stays exact: its hull lies in the tile's box), the greedy
   set cover of the tile, then greedy merging of the tile's leaves down to its target (below),
   once per merge cost, the costs sharing one memo of pair evaluations. Every tile voxel is in a
   leaf of its tile, so the leaves of all tiles cover V+.
3. **Merge task** (one per inner kd node, after its two children): the live nodes of both
   children with their heap entries (a pair's cost does not depend on the region: the hull of two
   nodes of a region lies in its box), plus every touching pair across the seam, evaluated now;
   greedy merging continues down to the node's target. The root merges down to one node.
4. **Order** (in the caller): each task's merges are one sequence; the family's merge order
   interleaves the sequences by cost (the cheapest next merge whose two nodes exist first), so
   H^n for every n is the set of nodes alive after the first N - n merges, and every H^n covers
   V+ (each merge replaces two nodes by the hull of their union).

Targets: a region at depth d >= 1 holding V_R of the V voxels stops at
``ceil(root_nodes * 2^(d-1) * V_R / V)`` nodes: each level halves the node count, the root starts
from about ``root_nodes`` nodes and runs the plain greedy below that, so the levels a flash
budget picks (n up to ~2000 at 64 KiB) are made by a greedy that sees the whole scene.

Memory: a tile task needs its tile's voxels and clusters (about 150 B per voxel); a merge task
the voxels of its region (24 B per voxel plus a bool grid and a summed-volume table of its box,
or sorted column keys when the box is large) and the live nodes of its children; the root holds
V+ once. Lattice coordinates are voxel indices minus ``base`` (the minimum index of V+) throughout.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from polycc.cover.clusters import build_clusters, neighbour_offsets, pack, solid_blocks
from polycc.cover.merge import MergeStage, StageNodes
from polycc.cover.setcover import greedy_set_cover
from polycc.geometry.lattice import CORNER_OFFSETS as CORNERS
from polycc.geometry.lattice import integer_planes, lattice_hull, voxel_corner_points, world_halfplanes
from polycc.parallel import Runner, Task

TILE_VOXELS = 32_768  # voxels per tile (at most)
ROOT_NODES = 2048  # about this many nodes reach the root stage
REF_SHIFT = 32  # a node ref is (stage id << REF_SHIFT) + position in its stage


@dataclass
class Region:
    """A node of the kd-tree of V+: ``rows`` of the grid's voxels (sorted), its depth, its children
    (ids, or None for a tile) and its parent (None for the root). Ids are pre-order positions."""

    id: int
    depth: int
    rows: np.ndarray
    children: tuple | None
    parent: int | None


def kd_regions(indices: np.ndarray, tile_voxels: int = TILE_VOXELS) -> list[Region]:
    """The kd-tree of the voxels ``indices`` ((V, 3), sorted): regions of more than ``tile_voxels``
    voxels are split at the median coordinate of the longest axis of their bounding box (voxels
    below the median go left). Pre-order list; region 0 is the root."""
    idx = np.asarray(indices, np.int64)
    out: list[Region] = []

    def split(rows: np.ndarray, depth: int, parent: int | None) -> int:
        me = len(out)
        out.append(Region(me, depth, rows, None, parent))
        if len(rows) <= tile_voxels:
            return me
        pts = idx[rows]
        ext = pts.max(axis=0) - pts.min(axis=0)
        for axis in np.argsort(-ext, kind="stable"):
            c = pts[:, axis]
            s = np.partition(c, len(c) // 2)[len(c) // 2]
            left = c < s
            if not left.any():  # the median is the minimum: cut above it instead
                above = c[c > s]
                if not len(above):
                    continue
                left = c <= s
            a = split(rows[left], depth + 1, me)
            b = split(rows[~left], depth + 1, me)
            out[me].children = (a, b)
            return me
        return me  # pragma: no cover - a region of one voxel position never has more than 1 voxel

    split(np.arange(len(idx), dtype=np.int64), 0, None)
    return out


def region_target(region: Region, n_voxels: int, root_nodes: int = ROOT_NODES) -> int:
    """Nodes a region's stage merges down to (module docstring); 1 for the root."""
    if region.parent is None:
        return 1
    return max(1, math.ceil(root_nodes * 2 ** (region.depth - 1) * len(region.rows) / n_voxels))


# ------------------------------------------------------------------ tasks (run on workers)


class Ragged:
    """A list of arrays (one per node, the same trailing shape and dtype) kept as one flat array and the
    row count of each, so that pickling it (to another worker, or through the parent of local processes)
    costs one buffer instead of one per node. Reads like the list: ``len``, ``[k]`` and iteration give
    views of the flat array.

    Measured on the 1.5M-splat room at 2.5 cm: a tile's hand-on (about 1,000 live nodes and 5,000 heap
    entries per cost) took 36 ms to pickle and 20-42 ms to unpickle as lists of small arrays and tuples,
    and the parent of ``--jobs`` processes unpickled and pickled each again on its way to the next task
    (a third process on 2 cores). Packed, ``--jobs 2`` built the cover in 72.2 s against 81.0, back to back,
    the same family bit for bit."""

    def __init__(self, arrays: list, flat: np.ndarray | None = None, counts: np.ndarray | None = None):
        if flat is None:
            counts = np.fromiter((len(a) for a in arrays), np.int64, len(arrays))
            flat = np.concatenate(arrays) if len(arrays) else np.zeros((0,), np.float64)
        self.flat, self.counts = flat, np.asarray(counts, np.int64)
        self._items = None  # views of flat, made on first read (the arrays given are not kept: no second copy)

    def _list(self) -> list:
        if self._items is None:
            self._items = np.split(self.flat, np.cumsum(self.counts)[:-1]) if len(self.counts) else []
        return self._items

    def __len__(self) -> int:
        return len(self.counts)

    def __getitem__(self, k):
        return self._list()[k]

    def __iter__(self):
        return iter(self._list())

    def __reduce__(self):
        return (Ragged, (None, self.flat, self.counts))


class Handoff:
    """What a merge stage hands on to the stage above it (its live nodes and their heap entries,
    :class:`~polycc.cover.merge.StageResult`), as a few flat arrays (:class:`Ragged`); :meth:`unpack` gives
    them back as they were, value for value (Python ints and floats where the stage had numpy scalars)."""

    def __init__(self, live: StageNodes, entries: list):
        self.ref = np.asarray(live.ref, np.int64)
        self.vertices = Ragged(live.vertices)
        self.normals = Ragged([p[0] for p in live.planes])
        self.offsets = Ragged([p[1] for p in live.planes])
        self.weight, self.volume, self.pattern = live.weight, live.volume, live.pattern
        cols = list(zip(*entries)) if entries else [(), (), (), (), ()]
        self.cost = np.asarray(cols[0], np.float64)
        self.pair = np.asarray([cols[1], cols[2]], np.int64).reshape(2, -1)
        self.kind = np.asarray(cols[3], np.int8)
        self.occupied = np.asarray([-1 if o is None else o for o in cols[4]], np.int64)  # -1: None (a count)

    def unpack(self) -> tuple[StageNodes, list]:
        live = StageNodes(self.ref.tolist(), list(self.vertices), list(zip(self.normals, self.offsets)),
                          self.weight, self.volume, self.pattern)
        occ = [None if o < 0 else o for o in self.occupied.tolist()]
        return live, list(zip(self.cost.tolist(), self.pair[0].tolist(), self.pair[1].tolist(),
                              self.kind.tolist(), occ))


def _world(nodes_vertices: list, nodes_planes: list, base, g, origin) -> tuple[Ragged, Ragged]:
    planes, verts = [], []
    for v, (nrm, _) in zip(nodes_vertices, nodes_planes):
        P, Vw = world_halfplanes(nrm, v + base, g, origin)
        planes.append(P)
        verts.append(Vw)
    return Ragged(planes), Ragged(verts)


def _record(res, base, g, origin, seconds: float) -> dict:
    """What the caller keeps of a stage: its merges, costs and the created nodes in world units."""
    planes, verts = _world(res.created.vertices, res.created.planes, base, g, origin)
    return {"merges": res.merges, "costs": res.costs, "refs": res.created.ref, "weight": res.created.weight,
            "volume": res.created.volume, "planes": planes, "vertices": verts,
            "pair_evaluations": res.pair_evaluations, "margin_rounds": res.margin_rounds, "seconds": seconds}


def prep_task(tile_id: int, rows: np.ndarray, voxels: np.ndarray, b: int, boxes: bool, base, g: float,
              origin) -> tuple[dict, tuple]:
    """Clusters and set cover of one tile (``voxels``: its voxels in lattice coordinates, sorted;
    ``rows``: their rows in the grid). Returns (kept: the leaves, in world units and as grid rows;
    passed on: the leaves as stage nodes and the tile's voxels)."""
    t0 = time.perf_counter()
    blo, blev, block = solid_blocks(voxels)
    in_block = block >= 0
    cl = build_clusters(voxels, b, boxes, centres=np.flatnonzero(~in_block) if in_block.any() else None)
    t1 = time.perf_counter()
    chosen = greedy_set_cover(cl, in_block if in_block.any() else None)
    t2 = time.perf_counter()
    offs = neighbour_offsets(cl.b)
    pats = cl.pattern[chosen]
    centres = cl.centre[chosen]
    keys, pplanes = {}, {}
    for p in np.unique(pats):
        rep = int(np.flatnonzero(cl.pattern == p)[0])
        mask = cl.neighbours[rep] >= 0
        keys[int(p)] = np.packbits(mask).tobytes()  # the same key for the same shape in every tile
        pplanes[int(p)] = integer_planes(lattice_hull(voxel_corner_points(offs[mask])))
    # solid blocks first (aligned cubes: zero waste, six planes), then the set cover's picks
    leaf_verts, leaf_planes, bkeys = [], [], []
    cube_planes: dict = {}
    for lo, L in zip(blo, blev):
        s = 1 << int(L)
        if int(L) not in cube_planes:
            cube_planes[int(L)] = integer_planes(lattice_hull(CORNERS * s))
        nrm, off = cube_planes[int(L)]
        leaf_verts.append(CORNERS * s + lo)
        leaf_planes.append((nrm, off + nrm @ lo))
        bkeys.append(b"block%d" % int(L))
    leaf_verts += [cl.hull_vertices[p] + voxels[v] for p, v in zip(pats, centres)]
    for p, v in zip(pats, centres):
        nrm, off = pplanes[int(p)]
        leaf_planes.append((nrm, off + nrm @ voxels[v]))
    ref0 = tile_id << REF_SHIFT
    vol_b = (8.0 ** blev).astype(np.float64)
    nodes = StageNodes([ref0 + k for k in range(len(blev) + len(chosen))], leaf_verts, leaf_planes,
                       np.concatenate([np.zeros(len(blev)), cl.weights[pats].astype(np.float64)]),
                       np.concatenate([vol_b, cl.volumes[pats].astype(np.float64)]),
                       bkeys + [keys[int(p)] for p in pats])
    wplanes, wverts = _world(leaf_verts, leaf_planes, base, g, origin)
    members = cl.neighbours[chosen]
    mask = members >= 0
    order_b = np.argsort(block[in_block], kind="stable")
    b_members = np.flatnonzero(in_block)[order_b]
    b_sizes = np.bincount(block[in_block], minlength=len(blev))
    b_centre = np.searchsorted(pack(voxels), pack(blo + (1 << blev)[:, None] // 2))  # the voxel at its centre
    kept = {"tile": tile_id, "leaf_voxel": rows[np.concatenate([b_centre, centres]).astype(np.int64)],
            "leaf_sizes": np.concatenate([b_sizes, mask.sum(axis=1)]),
            "leaf_members": rows[np.concatenate([b_members, members[mask]]).astype(np.int64)],
            "refs": nodes.ref, "weight": nodes.weight, "volume": nodes.volume,
            "planes": wplanes, "vertices": wverts, "patterns": len(cl.weights), "voxels": len(voxels),
            "seconds": {"clusters": t1 - t0, "set_cover": t2 - t1, "halfplanes": time.perf_counter() - t2}}
    return kept, (Handoff(nodes, []), voxels)


def tile_task(tile_id: int, costs: tuple, refresh: str, target: int, widen: bool, base, g: float, origin,
              prep: tuple) -> tuple[dict, dict]:
    """Greedy merging of one tile's leaves (``prep``: what :func:`prep_task` passed on) down to
    ``target`` nodes, once per cost in ``costs``. The costs share one memo of pair evaluations (both
    start from the same leaves: on a 2.5 cm room the second cost found every pair it evaluated there).
    Returns (kept: the stage record per cost, passed on: live nodes and heap entries per cost)."""
    nodes, voxels = prep[0].unpack()[0], prep[1]
    memo: dict = {}
    kept, passed = {}, {}
    for cost in costs:
        t = time.perf_counter()
        res = MergeStage(nodes, voxels, cost, refresh, ref_base=tile_id << REF_SHIFT, memo=memo).run(target, widen)
        kept[cost] = _record(res, base, g, origin, time.perf_counter() - t)
        passed[cost] = Handoff(res.live, res.entries)
    return kept, passed


def merge_task(region_id: int, voxels: np.ndarray, cost: str, refresh: str, target: int, widen: bool, base,
               g: float, origin, *children: dict) -> tuple[dict, dict]:
    """Continue merging the live nodes of the children of an inner kd node (``voxels``: the region's
    voxels, lattice coordinates). Returns (kept: the stage record, passed on: live nodes, entries)."""
    t = time.perf_counter()
    parts = [c[cost].unpack() for c in children]
    nodes = StageNodes.concatenate([p[0] for p in parts])
    entries, groups, off = [], [], 0
    for g_id, (live, ent) in enumerate(parts):
        entries += [(c, i + off, j + off, ex, occ) for c, i, j, ex, occ in ent]
        groups += [g_id] * len(live)
        off += len(live)
    st = MergeStage(nodes, voxels, cost, refresh, ref_base=region_id << REF_SHIFT, entries=entries,
                    groups=np.asarray(groups))
    res = st.run(target, widen)
    return _record(res, base, g, origin, time.perf_counter() - t), {cost: Handoff(res.live, res.entries)}


# ------------------------------------------------------------------ the graph and the family


def cover_graph(indices: np.ndarray, b: int, boxes: bool, costs: tuple, refresh: str, base, g: float, origin,
                tile_voxels: int = TILE_VOXELS, root_nodes: int = ROOT_NODES) -> tuple[list[Region], dict]:
    """(kd regions, task graph) of the tiled cover of ``indices`` (the grid's voxels). Keys:
    ``("prep", tile)``, ``("tile", tile)`` (every cost), ``("merge", region, cost)``; arguments are built
    when a task starts (callables), so the graph itself holds no copies of the voxels."""
    idx = np.asarray(indices, np.int64)
    regions = kd_regions(idx, tile_voxels)
    V = len(idx)
    base = np.asarray(base, np.int64)
    graph: dict = {}

    def stage_key(c: int, cost: str) -> tuple:
        return ("tile", c) if regions[c].children is None else ("merge", c, cost)

    def visit(r: Region):  # post-order: children first
        if r.children is not None:
            for c in r.children:
                visit(regions[c])
        target = region_target(r, V, root_nodes)
        widen = r.parent is None
        if r.children is None:
            graph[("prep", r.id)] = Task(prep_task, lambda r=r: (r.id, r.rows, idx[r.rows] - base, b, boxes, base, g,
                                                                 origin), weight=len(r.rows))
            graph[("tile", r.id)] = Task(tile_task, (r.id, tuple(costs), refresh, target, widen, base, g, origin),
                                         (("prep", r.id),), weight=len(r.rows) * len(costs))
        else:
            for cost in costs:
                graph[("merge", r.id, cost)] = Task(
                    merge_task, lambda r=r, cost=cost, target=target, widen=widen: (
                        r.id, idx[r.rows] - base, cost, refresh, target, widen, base, g, origin),
                    tuple(stage_key(c, cost) for c in r.children), weight=len(r.rows) / 4)

    visit(regions[0])
    return regions, graph


def order_merges(stage_records: list[dict], leaf_refs: list) -> tuple[list, np.ndarray, list]:
    """Interleave the stages' merge sequences into one family order: repeatedly the cheapest next
    merge (ties: lower stage position) whose two nodes exist. Returns (merges as ref pairs, their
    costs, created refs in order)."""
    import heapq

    exists = set(leaf_refs)
    heads = [0] * len(stage_records)
    waiting: dict = {}  # ref -> stages whose next merge needs it
    ready: list = []

    def offer(s: int):
        rec = stage_records[s]
        h = heads[s]
        if h >= len(rec["merges"]):
            return
        a, b = rec["merges"][h]
        missing = [r for r in (a, b) if r not in exists]
        if missing:
            waiting.setdefault(missing[0], []).append(s)
        else:
            heapq.heappush(ready, (float(rec["costs"][h]), s))

    for s in range(len(stage_records)):
        offer(s)
    merges, costs, created = [], [], []
    while ready:
        c, s = heapq.heappop(ready)
        rec = stage_records[s]
        h = heads[s]
        merges.append(rec["merges"][h])
        costs.append(c)
        ref = rec["refs"][h]
        created.append(ref)
        exists.add(ref)
        heads[s] += 1
        offer(s)
        for s2 in waiting.pop(ref, []):
            offer(s2)
    total = sum(len(r["merges"]) for r in stage_records)
    assert len(merges) == total, "internal: a stage's merge waits for a node no stage makes"
    return merges, np.asarray(costs, np.float64), created


def run_cover_graph(runner: Runner, indices, b, boxes, costs, refresh, base, g, origin, progress=None,
                    tile_voxels: int = TILE_VOXELS, root_nodes: int = ROOT_NODES) -> tuple[dict, dict]:
    """Run the tiled cover; returns (per cost: family arrays, statistics)."""
    t0 = time.perf_counter()
    regions, graph = cover_graph(indices, b, boxes, costs, refresh, base, g, origin, tile_voxels, root_nodes)
    res = runner.run(graph, progress)
    t_run = time.perf_counter() - t0
    tiles = [res[("prep", r.id)] for r in regions if r.children is None]  # pre-order
    leaf_refs = [ref for t in tiles for ref in t["refs"]]
    out = {}
    for cost in costs:
        t = time.perf_counter()
        stages = [res[("tile", r.id)][cost] for r in regions if r.children is None] + \
            [res[("merge", r.id, cost)] for r in regions if r.children is not None]
        merges, mcosts, created = order_merges(stages, leaf_refs)
        node_of = {ref: k for k, ref in enumerate(leaf_refs)}
        N = len(leaf_refs)
        node_of.update({ref: N + k for k, ref in enumerate(created)})
        made = {}
        for st in stages:
            for k, ref in enumerate(st["refs"]):
                made[ref] = (st, k)
        order = [made[ref] for ref in created]
        planes = [p for t_ in tiles for p in t_["planes"]] + [st["planes"][k] for st, k in order]
        verts = [v for t_ in tiles for v in t_["vertices"]] + [st["vertices"][k] for st, k in order]
        weight = np.concatenate([t_["weight"] for t_ in tiles] + [np.array([st["weight"][k] for st, k in order])])
        volume = np.concatenate([t_["volume"] for t_ in tiles] + [np.array([st["volume"][k] for st, k in order])])
        out[cost] = {
            "leaf_voxel": np.concatenate([t_["leaf_voxel"] for t_ in tiles]).astype(np.int64),
            "leaf_sizes": np.concatenate([t_["leaf_sizes"] for t_ in tiles]).astype(np.int64),
            "leaf_members": np.concatenate([t_["leaf_members"] for t_ in tiles]).astype(np.int64),
            "merges": np.array([[node_of[a], node_of[b_]] for a, b_ in merges], np.int64).reshape(-1, 2),
            "merge_costs": mcosts, "weight": weight, "volume": volume, "planes": planes, "vertices": verts,
            "pair_evaluations": int(sum(st["pair_evaluations"] for st in stages)),
            "margin_rounds": int(sum(st["margin_rounds"] for st in stages)),
            "merge_s": float(sum(st["seconds"] for st in stages)), "order_s": time.perf_counter() - t,
        }
    # task seconds per kd depth (tiles: prep + merge of every cost; inner nodes: merge), for projections
    by_depth: dict = {}
    for r in regions:
        d = by_depth.setdefault(str(r.depth), {"tasks": 0, "voxels": 0, "seconds": 0.0, "merges": 0})
        d["tasks"] += 1
        d["voxels"] += len(r.rows)
        recs = [res[("prep", r.id)]] + [res[("tile", r.id)][c] for c in costs] if r.children is None else \
            [res[("merge", r.id, c)] for c in costs]
        for rec in recs:
            sec = rec["seconds"]
            d["seconds"] += float(sum(sec.values()) if isinstance(sec, dict) else sec)
            d["merges"] += len(rec.get("merges", []))
    stats = {
        "by_depth": by_depth,
        "tiles": len(tiles), "regions": len(regions), "tile_voxels": int(tile_voxels), "root_nodes": int(root_nodes),
        "clusters_s": float(sum(t_["seconds"]["clusters"] for t_ in tiles)),
        "set_cover_s": float(sum(t_["seconds"]["set_cover"] for t_ in tiles)),
        "halfplanes_s": float(sum(t_["seconds"]["halfplanes"] for t_ in tiles)),
        "patterns": int(sum(t_["patterns"] for t_ in tiles)), "graph_wall_s": t_run,
        "workers": runner.workers, "where": runner.where,
    }
    return out, stats
