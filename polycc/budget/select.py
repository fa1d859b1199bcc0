"""Budgets: choose the cover H^n, reduce and quantize it so it fits flash and compute limits.

Pipeline for one candidate (n, T), T the cap of the shared normal table (None = uncapped):

1. materialise H^n from the merge family;
2. if its half-planes exceed the capacity, drop planes across all polytopes, cheapest
   added volume first (:mod:`polycc.budget.reduce`);
3. pack into the kernel's format 3 (:func:`polycc.onboard.layout.pack_scene`): normals snapped
   to the shared table (capped at T by spherical k-means), offsets rounded outward over the
   exact hull vertices of each polytope of H^n, int16 in power-of-two quanta;
4. measure conservativeness Vol(union)/Vol(V+) = 1 + Vol(union \\ V+)/Vol(V+) of the decoded
   polytopes, the wasted volume by Monte Carlo (:func:`polycc.geometry.union_volume.union_waste`).

Flash bytes are exact (:func:`polycc.onboard.layout.layout_bytes`):
48 + 4 planes + 16 n + 32 clusters + 12 normals.  The half-plane capacity of (n, T) is
(flash - 48 - 16 n - 32 C(n) - 12 T) // 4, with T = the number of distinct (snapped) normals
of H^n before reduction for the uncapped table (reduction only removes planes, so the stored
table is never larger).  A small T buys half-planes at 12 B per dropped normal but snaps
every plane to a coarser direction set: which one wins is measured, candidate by candidate.

Selection: the least conservative candidate among, for each T, the largest n that fits
without reduction, a few larger n that fit only after reduction and a few smaller n; among
candidates within the Monte Carlo 95 % half-width of the least conservative one, the fewest
polytopes (fastest on board).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from polycc.budget.cycle_model import _leaf_cost, worst_cycles
from polycc.budget.reduce import MIN_GAMMA, MIN_PLANES, polytope_stream, reduce_planes, stream_key
from polycc.cover.family import CoverFamily
from polycc.errors import PolyccError
from polycc.geometry.halfplanes import polytope_vertices
from polycc.geometry.lattice import unique_rows
from polycc.geometry.union_volume import in_voxels, union_waste
from polycc.native import MAX_PLANES as NATIVE_MAX_PLANES
from polycc.onboard.index import build_index, grid_box, index_bytes_at_least, index_slack
from polycc.onboard.layout import (
    DEFAULT_NORMAL_GRID,
    MAX_POLY_PLANES,
    PLANE_BYTES,
    PackedScene,
    SceneIndex,
    layout_bytes,
    n_clusters_for,
    pack_scene,
)
from polycc.parallel import init_worker, one_blas_thread

REDUCTION_FACTORS = (1.5, 2.0, 3.0, 4.0, 6.0)  # candidate n as multiples of the no-reduction n
CURVE_FACTORS = (0.5, 0.25, 0.1)  # smaller n also evaluated, for the trade-off curve
NORMAL_CAPS = (None, 1024, 256, 64)  # normal-table caps T tried (None = one entry per distinct normal)


@dataclass
class Budget:
    """flash_bytes: --flash-kb * 1024; max_halfplanes: --max-halfplanes (None = no limit);
    rate_cycles: Cortex-M4 cycles per evaluation allowed by --rate-hz and --cpu-share
    (None = no limit), turned into a half-plane cap for each n by the worst-case cycle model."""

    flash_bytes: int
    max_halfplanes: int | None = None
    rate_cycles: float | None = None
    clearance_cap: float | None = None  # D of the spatial index (None: no index, worst = every polytope)
    kappa: float = 100.0  # for the index's tightness slack
    index_reserve: dict | None = None  # n -> bytes the reduction leaves free for the index (capped tables, select)

    def caps(self, n: int, n_normals: int) -> dict[str, int]:
        """Half-plane capacity for n polytopes and a normal table of n_normals entries, per budget.
        With an index the rate budget bounds the index's certified worst case instead (in realise)."""
        reserve = self.index_reserve.get(n, 0) if self.index_reserve else 0
        caps = {"flash": (self.flash_bytes - reserve - data_bytes(n, 0, n_normals)) // PLANE_BYTES}
        if self.max_halfplanes is not None:
            caps["halfplanes"] = int(self.max_halfplanes)
        if self.rate_cycles is not None and self.clearance_cap is None:
            from polycc.budget.cycle_model import plane_budget

            caps["rate"] = plane_budget(self.rate_cycles, n)
        return caps

    def capacity(self, n: int, n_normals: int) -> int:
        return min(self.caps(n, n_normals).values())


def data_bytes(n_polys: int, n_planes: int, n_normals: int) -> int:
    """Exact flash bytes of a packed scene with these counts (clusters follow from n_polys)."""
    return layout_bytes(n_polys, n_planes, n_clusters_for(n_polys), n_normals)


def normal_keys(planes: np.ndarray, grid: int = DEFAULT_NORMAL_GRID) -> np.ndarray:
    """Integer id per half-plane row of the shared-table entry pack_scene snaps it to
    (direction m / |m|, m = round(grid n) / gcd), vectorised."""
    m = np.rint(np.asarray(planes)[:, :3] * grid).astype(np.int64)
    g = np.gcd.reduce(np.abs(m), axis=1)
    g[g == 0] = 1
    m //= g[:, None]
    lim = int(np.abs(m).max(initial=0))
    base = 2 * lim + 1
    if base ** 3 >= 2 ** 62:  # (unit normals: |m| <= grid, so only for a huge grid)
        _, ids = np.unique(m, axis=0, return_inverse=True)
        return ids.ravel()
    # one int64 per row, ordered as the rows lexicographically: the same ids as np.unique(m, axis=0), 4x faster
    code = ((m[:, 0] + lim) * base + (m[:, 1] + lim)) * base + (m[:, 2] + lim)
    _, ids = np.unique(code, return_inverse=True)
    return ids.ravel()


@dataclass
class Candidate:
    n: int
    max_normals: int | None  # table cap T passed to pack_scene (None = uncapped)
    packed: PackedScene
    planes_before: int  # half-planes of H^n before reduction
    normals_before: int  # distinct snapped normals of H^n before reduction
    dropped: int  # half-planes removed by the outward reduction
    merged: int  # half-planes of H^n stored as one because their snapped normals coincide
    union_volume: float
    union_ci: float
    conservativeness: float
    conservativeness_ci: float
    caps: dict = field(default_factory=dict)
    worst_cycles: float = 0.0  # certified (index) or every-polytope estimate, cycles
    meets_rate: bool = True  # the certified worst case fits --rate-hz / --cpu-share

    @property
    def n_planes(self) -> int:
        return self.packed.n_planes

    @property
    def n_normals(self) -> int:
        return self.packed.n_normals

    @property
    def bytes(self) -> int:
        return self.packed.flash_bytes()


def plane_counts(family: CoverFamily, per: np.ndarray | None = None) -> np.ndarray:
    """counts[n] = total half-planes of H^n for n = 1..N (index 0 unused), from the merge log.
    ``per`` (one count per node) replaces the family's plane counts (e.g. after merging the
    planes whose snapped normals coincide)."""
    N = family.n_max
    per = np.diff(family.plane_ptr).astype(np.int64) if per is None else np.asarray(per, np.int64)
    total = np.empty(N + 1, np.int64)
    total[N] = per[:N].sum()
    if N > 1:
        a, b = family.merges[:, 0], family.merges[:, 1]
        new = np.arange(N, N + len(family.merges))
        delta = per[new] - per[a] - per[b]
        total[N - 1 : 0 : -1] = total[N] + np.cumsum(delta)
    total[0] = 0
    return total


class _Normals:
    """Distinct snapped normals of H^n, for any n, from one vectorised key per family plane."""

    def __init__(self, family: CoverFamily):
        self.family = family
        self.keys = normal_keys(family.planes) if len(family.planes) else np.zeros(0, np.int64)
        self.total = int(self.keys.max()) + 1 if self.keys.size else 0
        self._cache: dict[int, int] = {}
        # planes per node once rows with the same snapped normal are merged (as pack_scene does)
        node = np.repeat(np.arange(len(family.plane_ptr) - 1), np.diff(family.plane_ptr))
        pairs = unique_rows(np.c_[node, self.keys]) if self.keys.size else np.zeros((0, 2), np.int64)
        self.merged_per_node = np.bincount(pairs[:, 0], minlength=len(family.plane_ptr) - 1)

    def count(self, n: int) -> int:
        if n not in self._cache:
            f = self.family
            k = f.active_nodes(n)
            idx = np.concatenate([np.arange(f.plane_ptr[i], f.plane_ptr[i + 1]) for i in k])
            self._cache[n] = int(np.unique(self.keys[idx]).size)
        return self._cache[n]


def realise(family: CoverFamily, n: int, max_normals: int | None, budget: Budget, normals_before: int,
            occupied_volume: float, mc_samples: int, seed: int = 0, caches: dict | None = None) -> Candidate | None:
    """Reduce, pack (format 3) and measure H^n with table cap T; None if it cannot fit.
    ``caches`` (one dict per selection) memoises drop costs and polytope records across candidates."""
    caches = {} if caches is None else caches
    polys = family.materialise(n)
    before = sum(len(p.halfplanes) for p in polys)
    t_eff = normals_before if max_normals is None else min(max_normals, normals_before)
    caps = budget.caps(n, t_eff)
    cap = min(caps.values())
    verts = [p.vertices for p in polys]
    # Merge the planes that pack_scene would store as one (same snapped normal) before reducing,
    # so that the capacity is spent on planes that are really stored.
    rows = [_merged_rows(p) for p in polys]
    for _ in range(8):  # pack_scene may close a snapped polytope with extra box planes, or the index may not
        # fit beside the planes: then retry tighter
        if cap < MIN_PLANES * n:
            return None
        red = reduce_planes([(h, p.vertices) for h, p in zip(rows, polys)], cap, per_polytope=MAX_POLY_PLANES,
                            cost_cache=caches.setdefault("drop_costs", {}))
        if red is None:
            return None
        packed = pack_scene(red[0], verts, max_normals=max_normals, record_cache=caches.setdefault("records", {}))
        over_planes = packed.n_planes - min(caps.values())
        if budget.clearance_cap is not None:
            ix = choose_index(packed, budget, budget.flash_bytes - packed.flash_bytes(),
                              cache=caches.setdefault("grid_box", {}))
            if ix is None:  # no index fits beside these planes: make room for the coarsest one
                coarse = build_index(packed, budget.clearance_cap, max(INDEX_CELLS), budget.kappa, max_bytes=0,
                                     box=grid_box(packed, float(np.float32(budget.clearance_cap))
                                                  + index_slack(packed, budget.kappa), caches["grid_box"]))
                over_bytes = packed.flash_bytes() + coarse.nbytes() - budget.flash_bytes
                cap -= max(-(-over_bytes // PLANE_BYTES), 1)
                continue
            packed = packed.with_index(ix)
        over_bytes = packed.flash_bytes() - budget.flash_bytes
        dropped = sum(len(h) for h in rows) - sum(len(h) for h in red[0])
        if over_planes <= 0 and over_bytes <= 0:
            break
        cap -= max(over_planes, -(-over_bytes // PLANE_BYTES), 1)
    else:
        return None
    worst = worst_cycles(packed, budget.kappa)
    meets = not (budget.clearance_cap is not None and budget.rate_cycles is not None and worst > budget.rate_cycles)
    # The byte model is exact and the table can only shrink (reduction removes planes, merging
    # removes duplicates, unused entries are dropped).
    assert packed.flash_bytes() == data_bytes(packed.n_polys, packed.n_planes, packed.n_normals) + (
        packed.index.nbytes() if packed.index is not None else 0), "byte model out of date"
    # (+6: pack_scene may add the axis normals to close an over-elongated polytope)
    assert packed.n_normals <= t_eff + 6 or max_normals is not None and packed.n_normals <= max_normals
    assert packed.flash_bytes() <= budget.flash_bytes
    order = packed.order if packed.order is not None else np.arange(packed.n_polys)
    stored = [h.astype(np.float64) for h in packed.polytopes()]
    boxes = []
    box_cache = caches.setdefault("boxes", {})  # candidates share most stored polytopes
    for h, p in zip(stored, [polys[i] for i in order]):
        key = (h.tobytes(), p.node)
        if key not in box_cache:
            v = polytope_vertices(h, p.vertices.mean(axis=0), MIN_GAMMA)
            if v is None:  # cannot happen for a packed (bounded) polytope; be loud if it does
                raise PolyccError(f"internal: stored polytope of node {p.node} is unbounded")
            box_cache[key] = (v.min(axis=0) - 1e-9, v.max(axis=0) + 1e-9)
        boxes.append(box_cache[key])
    if "occupied" not in caches:
        caches["occupied"] = in_voxels(family.grid_indices, family.origin, family.voxel_size)
    # V+ lies inside the union (certified), so Vol(union) = Vol(V+) + waste; the waste is
    # estimated directly, which is far less noisy than Vol(union) - Vol(V+)
    _, _, waste, wci = union_waste(stored, boxes, caches["occupied"], samples=mc_samples, seed=seed)
    return Candidate(n, max_normals, packed, before, normals_before, dropped, before - dropped - packed.n_planes,
                     occupied_volume + waste, wci, 1.0 + waste / occupied_volume, wci / occupied_volume, caps,
                     worst, meets)


INDEX_CELLS = (0.5, 1.0, 2.0)  # top cell sizes of the index tried, metres (powers of two)


def choose_index(packed: PackedScene, budget: Budget, max_bytes: int, cells=INDEX_CELLS,
                 cache: dict | None = None) -> SceneIndex | None:
    """The spatial index for ``packed`` (cap D = budget.clearance_cap), refined until its certified worst
    case meets the rate budget (or as far as ``max_bytes`` allows): among the top cell sizes, the one that
    meets the rate with the fewest bytes, else the one with the smallest worst case; None if no index
    fits ``max_bytes``."""
    best = None
    D = float(np.float32(budget.clearance_cap))
    box = grid_box(packed, D + index_slack(packed, budget.kappa), cache)
    for s in cells:
        if index_bytes_at_least(box, s, packed.n_polys) > max_bytes:
            continue  # its top cells alone cannot fit: not listed (the same choice; a capped table's retries in
            # realise asked for the 0.5 m grid of the 6M-splat room, 48 KB, six times with 5-6 KB free: 0.7 s each)
        try:
            ix = build_index(packed, budget.clearance_cap, s, budget.kappa, target=budget.rate_cycles,
                             max_bytes=max_bytes, cost=_leaf_cost, box=box)
        except PolyccError:
            continue
        if ix.nbytes() > max_bytes:
            continue
        w = worst_cycles(packed.with_index(ix), budget.kappa)
        meets = budget.rate_cycles is None or w <= budget.rate_cycles
        key = (not meets, ix.nbytes() if meets else w, w)
        if best is None or key < best[0]:
            best = (key, ix)
    return None if best is None else best[1]


def _largest(lo: int, hi: int, ok: Callable[[int], bool]) -> int:
    """Largest n in [lo, hi] with ok(n) by binary search (ok is taken as monotone), lo - 1 if none."""
    if hi < lo or not ok(lo):
        return lo - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if ok(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo


def candidate_ns(family: CoverFamily, budget: Budget, table: Callable[[int], int],
                 counts: np.ndarray | None = None, curve: bool = True) -> tuple[list[int], int]:
    """(n values worth evaluating, n0 = largest n that fits with no reduction, or 0), for a
    normal table of table(n) entries.  Plane counts and capacities are nearly monotone in n, so
    n0 and the largest n that can fit after reduction are found by binary search.  ``curve``
    adds the smaller n of CURVE_FACTORS (for the trade-off curve)."""
    N = family.n_max
    counts = plane_counts(family) if counts is None else counts
    cap = lambda n: budget.capacity(n, table(n))  # noqa: E731
    n0 = max(0, _largest(1, N, lambda n: int(counts[n]) <= cap(n)))
    if n0 == N:
        return sorted({N} | ({max(1, int(N * f)) for f in CURVE_FACTORS} if curve else set())), n0
    n_hi = max(0, _largest(1, N, lambda n: cap(n) >= MIN_PLANES * n))
    cands = {n0} if n0 else set()
    cands |= {max(1, int(n0 * f)) for f in CURVE_FACTORS if n0 and curve}
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
    normal_caps: tuple = NORMAL_CAPS,
    workers: int | None = None,
    stage_progress: Callable[[str, int, int], None] | None = None,
) -> tuple[Candidate, list[Candidate], str]:
    """Best candidate, every evaluated candidate, and the name of the binding budget.

    Candidates are pairs (n, T) over the table caps ``normal_caps``; a cap T is only tried at n
    where H^n has more than T distinct normals (otherwise it is the uncapped table). The uncapped
    candidates are realised first; a capped one is skipped when the uncapped candidates next to its n
    (below and above, where realised) all miss the rate budget (:func:`_capped_worth_trying`).
    ``workers``: local processes for a large family (None = every core); the result does not depend
    on it. ``stage_progress(stage, done, total)``: the parallel prefill's stages ("drop costs", then "pops"),
    which come before the candidates' ``progress``."""
    occ_vol = len(family.grid_indices) * family.voxel_size**3
    normals = _Normals(family)
    counts = plane_counts(family, normals.merged_per_node)
    pairs: list[tuple[int, int | None]] = []
    for T in normal_caps:
        table = normals.count if T is None else (lambda n, T=T: min(T, normals.count(n)))
        ns, _ = candidate_ns(family, budget, table, counts, curve=T is None)  # one curve, uncapped
        for n in ns:
            if T is not None and normals.count(n) <= T:
                continue  # the table is not capped at this n: same as uncapped
            pairs.append((n, T))
    pairs = sorted(set(pairs), key=lambda p: (p[0], -1 if p[1] is None else -p[1]))
    realise_all = _Realiser(family, normals, occ_vol, mc_samples, workers, counts)
    realise_all.stage_progress = stage_progress
    plain = [p for p in pairs if p[1] is None]
    step = (lambda base: (lambda d, _t: progress(base + d, len(pairs)))) if progress else (lambda base: None)
    done = realise_all(budget, plain, step(0))
    capped = [p for p in pairs if p[1] is not None and _capped_worth_trying(p[0], done, budget)]
    done = sorted(done + realise_all(_reserving(budget, capped, done), capped, step(len(plain))), key=_order)
    if progress:
        progress(len(pairs), len(pairs))
    if not done:
        raise PolyccError(impossible_budget_message(family, budget))
    # No candidate's certified worst case meets the rate: halve n (fewer polytopes, fewer per cell)
    # a few times, and cap the half-planes of every n so that the figure fits; the least conservative
    # of those that meet it is taken (the first halved n that met it was taken before, see _tightened).
    # If none does, keep the fastest candidate and say so in the binding budget.
    if not any(c.meets_rate for c in done):
        for _ in range(5):
            n = max(1, min(c.n for c in done) // 2)
            more = realise_all(budget, [(n, None)])
            done = sorted(done + more, key=_order)
            if n == 1 or any(c.meets_rate for c in more):
                break
        if budget.rate_cycles is not None:
            done = _tightened(budget, done, realise_all)
    if not any(c.meets_rate for c in done):
        best = min(done, key=lambda c: (c.worst_cycles, c.conservativeness))
        return best, done, (f"rate (missed: no candidate's certified worst case fits --rate-hz/--cpu-share; the "
                            f"fastest, {best.worst_cycles / 168:.0f} us, is taken)")
    done_all, done = done, [c for c in done if c.meets_rate]
    # least conservative; among candidates within the Monte Carlo 95 % half-width of it
    # (statistically tied) the fewest polytopes, which is the fastest on board
    low = min(done, key=lambda c: (c.conservativeness, -c.n))
    best = min((c for c in done if c.conservativeness <= low.conservativeness + low.conservativeness_ci),
               key=lambda c: (c.n, c.conservativeness))
    if best.caps.get("halfplanes") != budget.max_halfplanes:  # a cap of _tightened, not the user's
        return best, done_all, (f"rate (no candidate met the certified worst case with all its half-planes: "
                                f"capped at {best.caps['halfplanes']} so that it fits --rate-hz/--cpu-share)")
    return best, done_all, binding_text(family, best, done, done_all)


def _tightened(budget, done, realise_all) -> list[Candidate]:
    """``done`` plus, for every n realised so far and n = 1, the candidate with its half-planes capped so
    that even with every plane on the exp path the certified figure fits --rate-hz (outward reduction drops
    planes); the usual choice then takes the least conservative one that meets the rate.

    Regression: the first halved n that met the rate ended the search, and only the smallest n and n = 1
    were capped: the 150k-splat room at 2.5 cm got n = 1 (conservativeness 3.94) where n = 3 and n = 14 with
    capped planes met the rate at 1.04."""
    from dataclasses import replace

    from polycc.budget.cycle_model import PER_EXP_PLANE_CYCLES, PER_PLANE_CYCLES, indexed_cycles

    for n in sorted({c.n for c in done} | {1}, reverse=True):
        room = budget.rate_cycles - float(indexed_cycles(n, 0, 4, 0))
        cap = int(room // (PER_PLANE_CYCLES + PER_EXP_PLANE_CYCLES))
        if cap < MIN_PLANES * n:
            continue
        tight = replace(budget, max_halfplanes=min(cap, budget.max_halfplanes or cap))
        more = realise_all(tight, [(n, None)])
        done = done + [replace(c, meets_rate=c.worst_cycles <= budget.rate_cycles) for c in more]
    return sorted(done, key=_order)


def binding_text(family: CoverFamily, best: Candidate, done: list[Candidate],
                 done_all: list[Candidate] | None = None) -> str:
    """Which budget stopped the choice: its name first ('flash', 'halfplanes', 'rate' or 'none'),
    then why, for the summary."""
    if best.n == family.n_max and best.dropped == 0 and best.max_normals is None:
        return "none (the whole sub-cover fits)"
    slower = [c for c in (done_all or []) if not c.meets_rate]
    if slower and min(c.conservativeness for c in slower) < best.conservativeness - best.conservativeness_ci:
        return "rate (less conservative candidates miss the certified worst case budget)"
    tightest = min(best.caps, key=best.caps.get)
    slack = best.caps[tightest] - best.n_planes  # half-planes still free under that budget
    full = slack < max(8, 2 * best.n_planes / best.n)  # not even two more average polytopes fit
    larger = any(c.n > best.n for c in done)
    if full and larger:
        return (f"{tightest} (full; larger n fit only with a coarser normal table or fewer planes, "
                "and were more conservative)")
    if full or not larger:
        return tightest
    return "none (larger n fit, but were not measurably less conservative)"


def _order(c) -> tuple:
    return (c.n, -1 if c.max_normals is None else -c.max_normals)


def _capped_worth_trying(n: int, done: list[Candidate], budget: Budget) -> bool:
    """Whether a capped-table candidate at n can meet the rate budget, judged by the uncapped ones realised.

    A capped table only buys half-planes (12 B per normal dropped): at the same n the capped candidate
    keeps a prefix of the same greedy's drops, so at least the uncapped planes, on polytopes its coarser
    normals make no smaller, and the certified worst case grows with the planes listed per cell. So when
    the uncapped candidates next to n (the largest realised n' <= n and the smallest n' >= n, those that
    exist) all miss the rate, the capped one is not realised: on the 1.5M-splat room at 2.5 cm all seven
    missed it by 4-10x (543 000-686 000 cycles against 67 200) and took 327 of the 445 CPU seconds of the
    selection. Always tried without a rate budget or when nothing uncapped was realised."""
    if budget.rate_cycles is None or budget.clearance_cap is None or not done:
        return True
    below = [c for c in done if c.n <= n]
    above = [c for c in done if c.n >= n]
    near = ([max(below, key=lambda c: c.n)] if below else []) + ([min(above, key=lambda c: c.n)] if above else [])
    return any(c.meets_rate for c in near)


def _reserving(budget: Budget, capped: list, done: list[Candidate]) -> Budget:
    """``budget`` with, for each n of ``capped``, the index bytes of the uncapped candidates next to n that meet
    the rate (the most of them) left free by the reduction (:attr:`Budget.index_reserve`); unchanged without a
    rate budget and an index.

    A capped table buys half-planes, and the reduction spent every byte it freed on them: the index then had only
    what the retries of :func:`realise` cleared for the coarsest one. On the 6M-splat room at 5 cm all seven
    capped candidates missed the rate by 2-8x (150 000-511 000 cycles against 67 200) and took 60 of the
    selection's 100 s; with the reserve they come within 1.06-1.5x of it, and the selection took 49 s instead of
    80 (they still miss it, and the uncapped n = 351 is chosen as before). A capped candidate that meets the rate
    can now be found: before, one could only be chosen when nothing met the rate."""
    from dataclasses import replace

    if budget.rate_cycles is None or budget.clearance_cap is None or not capped:
        return budget
    reserve = {}
    for n, _ in capped:
        below = [c for c in done if c.n <= n]
        above = [c for c in done if c.n >= n]
        near = ([max(below, key=lambda c: c.n)] if below else []) + ([min(above, key=lambda c: c.n)] if above else [])
        sizes = [c.packed.index.nbytes() for c in near if c.meets_rate and c.packed.index is not None]
        if sizes:
            reserve[n] = max(sizes)
    return replace(budget, index_reserve=reserve or None)


def _realise_many(family, budget, pairs, normals_before, occ_vol, mc_samples, progress=None,
                  caches: dict | None = None) -> list[Candidate]:
    """Realise every pair of ``pairs`` in their order (increasing n). No candidate is skipped after one
    misses the rate budget: the certified worst case is not monotone in n (skipping the larger n after a
    miss cut the 2.5 cm room's cover from n = 26 to n = 5, conservativeness 1.33 -> 18). ``caches`` is
    shared by these candidates (drop costs and records of common polytopes)."""
    caches = {} if caches is None else caches
    out = []
    for i, (n, T) in enumerate(pairs):
        out.append(realise(family, n, T, budget, normals_before[n], occ_vol, mc_samples, caches=caches))
        if progress:
            progress(i + 1)
    return [c for c in out if c is not None]


PARALLEL_MIN_POLYTOPES = 500  # a family whose sub-cover is smaller is selected in this process (forks do not pay)
PREFILL_ROUNDS = 10  # rounds of :meth:`_Realiser._prefill` (each one fork of the workers, or none if small)
CHUNK_SHARE = 3  # a prefill round's next chunk: 1 / (this * workers) of the weight still left (:func:`_guided`)
STREAMS_IN_PROCESS = 64  # a prefill round of at most this many streams runs in this process (the same records)
PREFILL_OVERSHOOT = 1.25  # its guess of the next key takes this many more pending entries than drops missing
_FORKED: dict = {}  # what forked workers read (set before the fork, so nothing big is pickled)


def _merged_rows(p) -> np.ndarray:
    """The polytope's planes with those pack_scene would store as one (same snapped normal) merged, as
    :func:`realise` hands them to the reduction."""
    _, first = np.unique(normal_keys(p.halfplanes), return_index=True)
    return np.asarray(p.halfplanes[np.sort(first)], np.float64)


def _streams_chunk(idx: list[int], store: dict | None = None, work: list | None = None) -> list:
    """Make or extend the recorded greedies ``work[k]`` = (key, planes, vertices, lam) for k in ``idx``, kept in
    ``store`` (forked: both from ``_FORKED``; see :meth:`_Realiser._prefill`); returns them."""
    if store is None:
        store, work = _FORKED["store"], _FORKED["streams"]
    out = []
    for k in idx:
        key, h, v, lam = work[k]
        s = store[key] if key in store else polytope_stream(store, h, v, MAX_POLY_PLANES)
        if lam is not None:
            s.extend(lam)
        out.append(s)
    return out


def _stream_weight(m: int) -> float:
    """Relative cost of making the recorded greedy of a polytope of ``m`` planes (every plane's drop cost, and its
    first-phase drops): one C enumeration of plane triples up to :data:`polycc.native.MAX_PLANES` planes, one qhull
    per plane above it. Measured on the 1.5M-splat room at 2.5 cm: 3.4-7.4e-7 s per m (m + 50) up to 128 planes,
    5.1e-6 at 146 planes on average and 8.9e-6 at 271, so the qhull side is weighed m / 10 times more (the 18
    polytopes above 128 planes took 8.4 of the round's 10.1 s, and the old weight, m (m + 50) for all, put
    several in one chunk)."""
    w = m * (m + 50.0)
    return w * m / 10.0 if m > NATIVE_MAX_PLANES else w


def _pull_forked(_: int) -> list:
    return _pull(_FORKED["run"])


def _pull(st: dict, report: Callable[[int], None] | None = None) -> list[tuple[int, Candidate | None]]:
    """Realise the pairs of ``st`` one at a time, each time the next one no process has taken yet, in the order
    ``st["order"]`` (the counter ``st["next"]`` is shared by this process and the forked workers); (position in
    ``st["pairs"]``, candidate or None) of those this process took."""
    out = []
    nxt, done, pairs = st["next"], st["done"], st["pairs"]
    while True:
        with nxt.get_lock():
            i = nxt.value
            nxt.value += 1
        if i >= len(pairs):
            return out
        i = st["order"][i]
        n, T = pairs[i]
        out.append((i, realise(st["family"], n, T, st["budget"], st["counts"][n], st["occ_vol"], st["mc_samples"],
                               caches=st["caches"])))
        with done.get_lock():
            done.value += 1
            finished = done.value
        if report:
            report(finished)


class _Realiser:
    """Realises (n, T) pairs for one selection, with one cache for every call (drop costs, the recorded
    greedy streams, polytope records, boxes: the candidates of a selection share most polytopes).

    A family of at least :data:`PARALLEL_MIN_POLYTOPES` polytopes is spread over ``workers`` processes:
    first the recorded greedy of every polytope of the pairs that will be reduced, as far as their
    reductions will read it (:meth:`_prefill`: one qhull per drop cost, the bulk of the work; each polytope
    once, on whichever worker is free), then the pairs themselves, each taken by the next worker to come free
    (:meth:`_pulled`), every worker starting from the cache with those records in it. The workers are
    forked, so they read the family and the cache without a copy. The result does not depend on
    ``workers``: :func:`realise` is a pure function of its pair, and the cache gives the same result bit for
    bit (the records are computed by the same code on the same float64 inputs).

    Before the prefill, the candidates' workers each extended the records they needed themselves: the
    polytopes two runs share were reduced twice, and 2 workers took 44 s where one took 63 s (the 1.5M-splat
    room at 2.5 cm); now 37.6 s, the same candidates bit for bit."""

    def __init__(self, family, normals, occ_vol, mc_samples, workers, counts):
        from polycc.parallel import available_cores

        self.family, self.normals, self.occ_vol, self.mc_samples = family, normals, occ_vol, mc_samples
        self.counts = counts  # merged half-planes of H^n
        self.workers = available_cores() if workers is None else max(1, int(workers))
        self.caches: dict = {}
        self.stage_progress: Callable[[str, int, int], None] | None = None

    def _parallel(self, pairs) -> bool:
        import multiprocessing as mp

        return (self.workers > 1 and len(pairs) > 1 and self.family.n_max >= PARALLEL_MIN_POLYTOPES
                and "fork" in mp.get_all_start_methods())

    def __call__(self, budget: Budget, pairs, progress: Callable[[int, int], None] | None = None):
        pairs = list(pairs)
        before = {n: self.normals.count(n) for n, _ in pairs}
        report = (lambda i: progress(i, len(pairs))) if progress else None
        if not self._parallel(pairs):
            return _realise_many(self.family, budget, pairs, before, self.occ_vol, self.mc_samples, report,
                                 caches=self.caches)
        self._prefill(budget, pairs, before)
        return self._pulled(budget, pairs, before, report)

    def _prefill(self, budget, pairs, before) -> None:
        """Fill the cache with the recorded greedy (:class:`polycc.budget.reduce._Stream`) of every polytope the
        reductions of these pairs will read, as far as they will read it, computed polytope by polytope in
        parallel (each once, however many candidates share it), so that the candidates replay them.

        How far: a pair at n must drop about D = (its merged planes - the first phase's drops - its capacity)
        planes in the global phase, and when every stream of H^n is recorded past key lam with at least D drops
        at keys <= lam, its greedy reads nothing unrecorded (:meth:`~polycc.budget.reduce._Stream.upto`). lam
        is raised in rounds, each guessed from the heaps' pending keys (mostly lower bounds, so a guess falls
        short rather than far beyond); what is still missing after :data:`PREFILL_ROUNDS` rounds, or what a
        tighter retry of a candidate needs, its worker computes on demand, as without the prefill."""
        store = self.caches.setdefault("drop_costs", {})
        need: dict[int, tuple[int, list]] = {}
        todo: dict = {}
        for n in sorted({n for n, _ in pairs}):
            cap = budget.capacity(n, max(before[n] if T is None else min(T, before[n]) for m, T in pairs if m == n))
            reduced = self.counts[n] > 0.8 * cap  # the index's bytes may force it near the cap
            polys = self.family.materialise(n)
            rows = [_merged_rows(p) for p in polys]
            if not (reduced or any(len(h) > MAX_POLY_PLANES for h in rows)):
                continue
            keys = []
            for p, h in zip(polys, rows):
                v = np.asarray(p.vertices, np.float64)
                key = stream_key(h, v, MAX_POLY_PLANES)
                keys.append(key)
                if key not in store:
                    todo[key] = (key, h, v, None)
            need[n] = (int(self.counts[n]) - cap, keys)
        say = self.stage_progress or (lambda *a: None)
        self._streams(list(todo.values()), [_stream_weight(len(h)) for _, h, _, _ in todo.values()],
                      lambda d, t: say("drop costs", d, t))
        lam = {n: -np.inf for n in need}
        for _ in range(PREFILL_ROUNDS):
            target: dict = {}
            for n, (d, keys) in need.items():
                streams = [store[k] for k in keys]
                d -= sum(len(s.pre_costs) for s in streams)
                got = sum(s.upto(lam[n])[0] for s in streams)
                if got >= d:
                    continue
                guess = sorted(g for s in streams for g in s.pending(lam[n]) + [s.upto(lam[n])[1]] if g < np.inf)
                if not guess:
                    continue
                lam[n] = guess[min(len(guess) - 1, int(PREFILL_OVERSHOOT * (d - got)))]
                for k in keys:
                    target[k] = max(target.get(k, -np.inf), lam[n])
            work = [(k, None, None, t) for k, t in target.items() if not store[k].upto(t)[2]]
            if not work:
                break
            say("pops", 0, 1)
            self._streams(work, [(len(store[k].planes) + 50.0) * (1 + sum(e[0] <= t for e in store[k].heap))
                                 for k, _, _, t in work])

    def _streams(self, work: list, weights: list[float], report: Callable[[int, int], None] | None = None) -> None:
        """Run :func:`_streams_chunk` over ``work`` on ``workers`` forked processes (in this process when ``work``
        has at most :data:`STREAMS_IN_PROCESS` streams) and keep the results. The
        work is cut into chunks heaviest first by ``weights``, shrinking (:func:`_guided`), which the pool hands
        out as workers come free: a qhull's cost grows with the planes, and the number of pops a stream needs is
        only guessed, so fixed shares came out 1.4-2.4x apart."""
        if not work:
            return
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        store = self.caches["drop_costs"]
        if len(work) <= STREAMS_IN_PROCESS:  # a late prefill round: a fork of this process costs more than it
            for k, st in enumerate(_streams_chunk(list(range(len(work))), store, work)):
                store[work[k][0]] = st
            if report:
                report(len(work), len(work))
            return
        order = sorted(range(len(work)), key=lambda k: -weights[k])
        chunks = _guided(order, [weights[k] for k in order], self.workers)
        _FORKED.clear()
        _FORKED.update(store=store, streams=work)
        try:
            with ProcessPoolExecutor(min(self.workers, len(chunks)), mp_context=mp.get_context("fork"),
                                     initializer=init_worker) as ex:
                futs = [ex.submit(_streams_chunk, c) for c in chunks]
                finished = 0
                for f in as_completed(futs):
                    finished += len(chunks[futs.index(f)])
                    if report:
                        report(finished, len(work))
                results = [f.result() for f in futs]
        finally:
            _FORKED.clear()
        for chunk, streams in zip(chunks, results):
            for k, st in zip(chunk, streams):
                store[work[k][0]] = st

    def _pulled(self, budget, pairs, before, report) -> list[Candidate]:
        """The pairs realised by this process and ``workers - 1`` forked ones, each taking the next pair not yet
        taken as it comes free (:func:`_pull`), the largest n first (the costliest, roughly: the last to finish
        then waits for a small one); returned in the order of ``pairs``. The forked workers read the family and
        the cache (with the prefill's records) without a copy; this process keeps its own records in the cache.

        Before, the pairs were cut into contiguous runs of n, one per worker, weighed by their half-planes^1.5:
        on the 1.5M-splat room at 2.5 cm the two runs took 10.7 and 6.4 s one after the other (one by one:
        0.6-1.1 s at n <= 52, 1.6-2.9 s up to n = 315, 2.4 and 4.0 s at n = 420 and 630), and 13.0 s side by side
        where the shorter run took less; now 11.3 s. Side by side each candidate takes about a third longer than
        alone (both processes fetch from memory; the prefill's qhulls do not slow each other down)."""
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        ctx = mp.get_context("fork")
        st = dict(family=self.family, budget=budget, pairs=pairs, counts=before, occ_vol=self.occ_vol,
                  mc_samples=self.mc_samples, caches=self.caches, next=ctx.Value("i", 0), done=ctx.Value("i", 0),
                  order=sorted(range(len(pairs)), key=lambda i: -pairs[i][0]))
        _FORKED.clear()
        _FORKED.update(run=st)
        try:
            if self.workers == 1:
                got = dict(_pull(st, report))
            else:
                with ProcessPoolExecutor(self.workers - 1, mp_context=ctx, initializer=init_worker) as ex, \
                        one_blas_thread():  # this process realises candidates beside its workers
                    futs = [ex.submit(_pull_forked, k) for k in range(self.workers - 1)]
                    got = dict(_pull(st, report))
                    for f in futs:
                        got.update(f.result())
        finally:
            _FORKED.clear()
        if report:
            report(len(pairs))
        return [got[i] for i in range(len(pairs)) if got[i] is not None]


def _guided(items: list, weights: list[float], workers: int) -> list[list]:
    """``items`` (heaviest first) cut in their order into chunks of about 1 / (:data:`CHUNK_SHARE` * workers) of
    the weight still left, at least one item each (and at least 1 % of the total): large chunks first, small ones
    last, so that workers taking the next chunk as they come free finish close together even where the weights
    are guesses (guided self-scheduling). Before, 4 equal chunks per worker: a round's last chunk left the
    other workers idle for up to an eighth of it."""
    total = float(sum(weights)) or 1.0
    left, out, run, acc = total, [], [], 0.0
    for item, w in zip(items, weights):
        run.append(item)
        acc += w
        if acc >= max(left / (CHUNK_SHARE * workers), 0.01 * total):
            out.append(run)
            left -= acc
            run, acc = [], 0.0
    if run:
        out.append(run)
    return out


def impossible_budget_message(family: CoverFamily, budget: Budget) -> str:
    """Explain an impossible budget and give the smallest one that would work."""
    p1 = family.materialise(1)[0]
    need_planes = len(p1.halfplanes)
    for cap in range(MIN_PLANES, len(p1.halfplanes) + 1):
        if reduce_planes([(p1.halfplanes, p1.vertices)], cap, per_polytope=MAX_POLY_PLANES) is not None:
            need_planes = cap
            break
    need = data_bytes(1, need_planes, need_planes)
    parts = [f"even one polytope needs {need_planes} half-planes = {need} bytes ({need / 1024:.3f} KiB)"]
    if budget.flash_bytes < need:
        parts.append(f"--flash-kb {budget.flash_bytes / 1024:g} is too small: use "
                     f"--flash-kb {math.ceil(need / 1024 * 100) / 100:g} or more")
    if budget.max_halfplanes is not None and budget.max_halfplanes < need_planes:
        parts.append(f"--max-halfplanes {budget.max_halfplanes} is too small: use {need_planes} or more")
    if budget.rate_cycles is not None and budget.clearance_cap is not None:
        parts.append("or no candidate's certified worst case fits --rate-hz/--cpu-share: lower --rate-hz, raise "
                     "--cpu-share or --flash-kb (a finer index), or lower --clearance-cap")
    elif budget.rate_cycles is not None and budget.caps(1, need_planes)["rate"] < need_planes:
        parts.append("--rate-hz is too high for even one polytope: lower it")
    return "; ".join(parts)
