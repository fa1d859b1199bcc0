"""Budgets: choose the cover H^n, reduce and quantize it so it fits flash and compute limits.

Pipeline for one candidate n (every step outward, so every occupied voxel stays inside):

1. materialise H^n from the merge family;
2. if its half-planes exceed the capacity, drop planes across all polytopes, cheapest
   added volume first (:mod:`polycc.reduce`);
3. round each half-plane to float32 with |n| <= 1 and the offset rounded up over the
   polytope's vertices (:mod:`polycc.quantize`);
4. pack into the kernel's layout and measure conservativeness Vol(union)/Vol(V+) by
   Monte Carlo (:mod:`polycc.union_volume`).

Selection: the least conservative candidate among the largest n that fits without
reduction and a few larger n that fit only after reduction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from polycc.cover_family import CoverFamily
from polycc.errors import PolyccError
from polycc.quantize import quantize_float32
from polycc.reduce import MIN_PLANES, reduce_planes
from polycc.scene_layout import CLUSTER_BYTES, HEADER, MAX_POLY_PLANES, PLANE_BYTES, POLY_BYTES, PackedScene, pack_scene
from polycc.union_volume import union_volume

ROOT_BYTES = HEADER.size + 12  # root record on the Cortex-M4 (three 32-bit pointers)
REDUCTION_FACTORS = (1.5, 2.0, 3.0, 4.0, 6.0)  # candidate n as multiples of the no-reduction n
CURVE_FACTORS = (0.5, 0.25, 0.1)  # smaller n also evaluated, for the trade-off curve


@dataclass
class Budget:
    """flash_bytes: --flash-kb * 1024; max_halfplanes: --max-halfplanes (None = no limit);
    rate_cycles: Cortex-M4 cycles per evaluation allowed by --rate-hz and --cpu-share
    (None = no limit), turned into a half-plane cap for each n by the worst-case cycle model."""

    flash_bytes: int
    max_halfplanes: int | None = None
    rate_cycles: float | None = None

    def caps(self, n: int) -> dict[str, int]:
        """Half-plane capacity for n polytopes, per budget."""
        caps = {"flash": (self.flash_bytes - ROOT_BYTES - n * POLY_BYTES - n_clusters(n) * CLUSTER_BYTES) // PLANE_BYTES}
        if self.max_halfplanes is not None:
            caps["halfplanes"] = int(self.max_halfplanes)
        if self.rate_cycles is not None:
            from polycc.cycle_model import plane_budget

            caps["rate"] = plane_budget(self.rate_cycles, n)
        return caps

    def capacity(self, n: int) -> int:
        return min(self.caps(n).values())


def n_clusters(n: int) -> int:
    """Culling clusters pack_scene makes for n polytopes (its median splits depend on n only)."""
    leaf = max(4, math.ceil(math.sqrt(n)))
    count, todo = 0, [n]
    while todo:
        m = todo.pop()
        if m <= leaf:
            count += 1
        else:
            todo += [m - m // 2, m // 2]
    return count


def data_bytes(n_polys: int, n_planes: int) -> int:
    return ROOT_BYTES + n_polys * POLY_BYTES + n_clusters(n_polys) * CLUSTER_BYTES + n_planes * PLANE_BYTES


@dataclass
class Candidate:
    n: int
    packed: PackedScene
    planes_before: int  # half-planes of H^n before reduction
    dropped: int
    union_volume: float
    union_ci: float
    conservativeness: float
    conservativeness_ci: float
    caps: dict = field(default_factory=dict)

    @property
    def n_planes(self) -> int:
        return self.packed.n_planes

    @property
    def bytes(self) -> int:
        return self.packed.flash_bytes()


def plane_counts(family: CoverFamily) -> np.ndarray:
    """counts[n] = total half-planes of H^n for n = 1..N (index 0 unused), from the merge log."""
    N = family.n_max
    per = np.diff(family.plane_ptr).astype(np.int64)
    total = np.empty(N + 1, np.int64)
    total[N] = per[:N].sum()
    if N > 1:
        a, b = family.merges[:, 0], family.merges[:, 1]
        new = np.arange(N, N + len(family.merges))
        delta = per[new] - per[a] - per[b]
        total[N - 1 : 0 : -1] = total[N] + np.cumsum(delta)
    total[0] = 0
    return total


def realise(family: CoverFamily, n: int, cap: int, occupied_volume: float, mc_samples: int, seed: int = 0) -> Candidate | None:
    """Reduce, quantize, pack and measure H^n under a half-plane capacity; None if it cannot fit."""
    polys = family.materialise(n)
    before = sum(len(p.halfplanes) for p in polys)
    red = reduce_planes([(p.halfplanes, p.vertices) for p in polys], cap, per_polytope=MAX_POLY_PLANES)
    if red is None:
        return None
    reduced, _ = red
    stored = [quantize_float32(h, p.vertices) for h, p in zip(reduced, polys)]
    packed = pack_scene(stored)
    assert packed.flash_bytes() == data_bytes(packed.n_polys, packed.n_planes), "byte model out of date with pack_scene"
    # Bounding boxes of the stored polytopes from their (enlarged) vertices.
    from polycc.reduce import polytope_vertices

    boxes = []
    order = packed.order if packed.order is not None else np.arange(packed.n_polys)
    for h, p in zip(packed.polytopes(), [polys[i] for i in order]):
        v = polytope_vertices(h.astype(np.float64), p.vertices.mean(axis=0))
        if v is None:  # cannot happen for a packed (bounded) polytope; be loud if it does
            raise PolyccError(f"internal: stored polytope of node {p.node} is unbounded")
        boxes.append((v.min(axis=0) - 1e-9, v.max(axis=0) + 1e-9))
    vol, ci = union_volume([h.astype(np.float64) for h in packed.polytopes()], boxes, samples=mc_samples, seed=seed)
    return Candidate(n, packed, before, before - packed.n_planes, vol, ci, vol / occupied_volume, ci / occupied_volume)


def candidate_ns(family: CoverFamily, budget: Budget) -> tuple[list[int], int]:
    """(n values worth evaluating, n0 = largest n that fits with no reduction, or 0)."""
    N = family.n_max
    counts = plane_counts(family)
    ns = np.arange(1, N + 1)
    caps = np.array([budget.capacity(int(n)) for n in ns])
    fits = counts[1:] <= caps
    n0 = int(ns[fits].max()) if fits.any() else 0
    if n0 == N:
        return sorted({N} | {max(1, int(N * f)) for f in CURVE_FACTORS}), n0
    feasible_hi = ns[caps >= MIN_PLANES * ns]
    n_hi = int(feasible_hi.max()) if feasible_hi.size else 0
    cands = {n0} if n0 else set()
    cands |= {max(1, int(n0 * f)) for f in CURVE_FACTORS if n0}
    base = max(n0, 1)
    for f in REDUCTION_FACTORS:
        n = min(N, n_hi, int(math.ceil(base * f)))
        if n > n0:
            cands.add(n)
    if not cands and n_hi:
        cands.add(min(n_hi, N))
    return sorted(cands), n0


def select(
    family: CoverFamily,
    budget: Budget,
    mc_samples: int = 100_000,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Candidate, list[Candidate], str]:
    """Best candidate, every evaluated candidate, and the name of the binding budget."""
    occ_vol = len(family.grid_indices) * family.voxel_size**3
    ns, n0 = candidate_ns(family, budget)
    done: list[Candidate] = []
    for i, n in enumerate(ns):
        c = realise(family, n, budget.capacity(n), occ_vol, mc_samples)
        if c is not None:
            c.caps = budget.caps(n)
            done.append(c)
        if progress:
            progress(i + 1, len(ns))
    if not done:
        raise PolyccError(impossible_budget_message(family, budget))
    best = min(done, key=lambda c: (c.conservativeness, -c.n))
    if best.n == family.n_max and best.dropped == 0:
        binding = "none (the whole sub-cover fits)"
    else:
        caps = best.caps
        binding = min(caps, key=caps.get)
    return best, done, binding


def impossible_budget_message(family: CoverFamily, budget: Budget) -> str:
    """Explain an impossible budget and give the smallest one that would work."""
    p1 = family.materialise(1)[0]
    need_planes = len(p1.halfplanes)
    for cap in range(MIN_PLANES, len(p1.halfplanes) + 1):
        if reduce_planes([(p1.halfplanes, p1.vertices)], cap, per_polytope=MAX_POLY_PLANES) is not None:
            need_planes = cap
            break
    need = data_bytes(1, need_planes)
    parts = [f"even one polytope needs {need_planes} half-planes = {need} bytes ({need / 1024:.3f} KiB)"]
    if budget.flash_bytes < need:
        parts.append(f"--flash-kb {budget.flash_bytes / 1024:g} is too small: use --flash-kb {math.ceil(need / 1024 * 100) / 100:g} or more")
    if budget.max_halfplanes is not None and budget.max_halfplanes < need_planes:
        parts.append(f"--max-halfplanes {budget.max_halfplanes} is too small: use {need_planes} or more")
    if budget.rate_cycles is not None and budget.caps(1)["rate"] < need_planes:
        parts.append("--rate-hz is too high for even one polytope: lower it")
    return "; ".join(parts)
