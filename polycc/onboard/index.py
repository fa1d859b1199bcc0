"""Build-time spatial index of a packed scene: a uniform grid whose cells list the only polytopes the
kernel evaluates there, with a clearance cap D (docs/barrier.md section 9).  World frame, metres.

Certificate (exact reals, decoded values; float64 here with outward cushions):

* the kernel maps p to cell (i, j, k) = floor((p - origin) / s) in float32; every cell is certified
  over its box grown by ``eps`` (the float32 rounding of that lookup, a few ulps of |p|);
* per cell box (centre c, half side h): U = min_k max_l (g_kl(c) + h |n_kl|_1) is the exact maximum
  of min_k phi_k over the box (a convex function of p has its maximum over a box at a corner; the
  max of linear functions over the box is the per-plane maximum);
* polytope k is LEFT OUT only if LB_k >= min(U, D) + slack, LB_k = max(max_l (g_kl(c) - h |n_kl|_1),
  gamma_k (dist(box, c_k) - R_k)), a lower bound of phi_k over the box;
* then min(psi0, D) over the listed polytopes stays below h = min_k phi_k (section 9);
* outside the grid box B every polytope has phi_k >= gamma_k (|p - c_k| - R_k) >= D + slack, so the
  kernel returns D there with no polytope evaluated.

The certified worst case of one evaluation is the largest cycle count of the cycle model over the
cells (every listed polytope entered, evaluated and all its half-planes scanned) and the outside path.
"""

from __future__ import annotations

import math

import numpy as np

from polycc.errors import PolyccError
from polycc.onboard.layout import PackedScene, SceneIndex, index_bytes

DEFAULT_CLEARANCE_CAP = 0.3  # m (measured: the make-demo build keeps n = 396 at 500 Hz / 20 %; 0.6 m forces n = 158)
DEFAULT_CELLS = (0.25, 0.5, 1.0)  # cell sizes s (powers of two, metres) tried by choose_index
NEGLIGIBLE_NATS = 17.0
_CUSHION = 1e-9  # relative outward cushion of the float64 geometry (errors are ~1e-15 relative)
SPLIT_BATCH_MAX = 64  # leaves whose children build_index lists in one pass (see there)
GRID_PAIRS_PER_PASS = 1 << 21  # (cell, half-plane) pairs of the top cells listed in one pass, about




def _poly_geometry(packed: PackedScene):
    P = packed.polys
    c = np.stack([P["cx"], P["cy"], P["cz"]], axis=1).astype(np.float64)
    R = P["r_out"].astype(np.float64)
    ig = P["inv_gamma"].astype(np.float64)
    return c, R, ig


def lookup_eps(extent: float) -> float:
    """Bound on how far (metres) outside its box a point can be that the float32 lookup maps into a
    cell: one rounding of p - origin (half an ulp of numbers below ``extent``), generously 2^-22 extent."""
    return 2.0**-22 * (extent + 1.0)


def _face_bound(n: np.ndarray, d: np.ndarray, e: np.ndarray, delta: float) -> float:
    """X such that phi(p) = max_l (n_l . p - d_l) >= delta whenever e . p >= X (|p|_inf <= POS_MAX),
    e a unit axis vector.  From the dual of max e.p s.t. n_l.p <= d_l + delta: with lambda >= 0,
    Lam = sum lambda, r = sum lambda_l n_l - e (computed exactly in rationals),
    Lam phi(p) >= sum lambda_l g_l(p) = e.p + r.p - lambda.d, so X = Lam delta + lambda.d + |r|_1 POS_MAX
    (rounded up) is certified whatever the LP solver's accuracy."""
    from fractions import Fraction

    from polycc.geometry.lp_raw import linprog_highs

    # linprog(-e, A_ub=n, b_ub=d + delta, bounds free, method="highs"): its status and marginals, bit for bit
    status, _, marginals = linprog_highs(-np.asarray(e, np.float64), n, d + delta, _FREE3_LB, _FREE3_UB)
    if status != 0:
        raise PolyccError("index: the grid box LP failed (an unbounded polytope?)")
    lam = np.maximum(-np.asarray(marginals, np.float64), 0.0)
    F = Fraction
    lamf = [F(float(x)) for x in lam]
    Lam = sum(lamf)
    if Lam <= 0:
        raise PolyccError("index: degenerate grid box certificate")
    r = [sum(lf * F(float(n[i, j])) for i, lf in enumerate(lamf)) - F(float(e[j])) for j in range(3)]
    lam_d = sum(lf * F(float(di)) for lf, di in zip(lamf, d))
    X = Lam * F(delta) + lam_d + sum(abs(x) for x in r) * F(_POS_MAX)
    out = float(X)
    return out if F(out) >= X else float(np.nextafter(out, np.inf))


_POS_MAX = 1.0e5  # POLYCC_POS_MAX: larger coordinates are invalid input
_FREE3_LB = np.full(3, -np.inf)
_FREE3_UB = np.full(3, np.inf)


GRID_BOX_MARGIN = 1e-3  # m: a polytope whose ball bound stays this far inside the box so far gets no LP


def grid_box(packed: PackedScene, delta: float, cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) such that every polytope has phi_k(p) >= delta at every p outside [lo, hi]
    (certified per face): the union of the polytopes grown by delta, boxed.  A polytope with the axis
    plane +-e itself (n = e exactly) needs no LP: phi >= +-p_i - d >= delta beyond d + delta.
    Per face of the box, the polytopes are taken in decreasing order of their ball bound (phi_k >=
    (|p - c_k| - R_k) / ig_k >= delta beyond rho_k = R_k + delta ig_k from c_k, cushioned outward) and the
    LP stops at the first polytope whose ball bound lies ``GRID_BOX_MARGIN`` inside the face found so far:
    the rest are certified by their ball alone (the 6M-splat room's selection: 1 025 LPs instead of 10 708), and
    the face is the largest LP bound unless an LP certificate is looser than the ball by more than the margin.
    ``cache`` (a dict kept by the caller) memoises the per-polytope faces across packings."""
    from fractions import Fraction

    pm = packed.plane_matrix().astype(np.float64)
    c, R, ig = _poly_geometry(packed)
    rho = (R + delta * ig) * (1 + 1e-6) + 1e-6  # (dist - R) / ig >= delta beyond rho, rounding cushioned
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    first, count = packed.polys["first"].astype(np.int64), packed.polys["count"].astype(np.int64)

    def face(k: int, j: int, sign: float) -> float:
        rows = pm[first[k] : first[k] + count[k]]
        key = (rows.tobytes(), float(delta), j, sign)
        if cache is not None and key in cache:
            return cache[key]
        e = np.zeros(3)
        e[j] = sign
        exact = np.nonzero(np.all(rows[:, :3] == e, axis=1))[0]
        if len(exact):  # X = d + delta, rounded up (exact rationals)
            X = Fraction(float(np.min(rows[exact, 3]))) + Fraction(delta)
            b = float(X)
            b = b if Fraction(b) >= X else float(np.nextafter(b, np.inf))
        else:
            b = _face_bound(rows[:, :3], rows[:, 3], e, delta)
        if cache is not None:
            cache[key] = b
        return b

    for j in range(3):
        for sign in (1.0, -1.0):
            ub = sign * c[:, j] + rho  # sign * p_j <= ub_k wherever phi_k < delta
            best = -np.inf
            for k in np.argsort(-ub, kind="stable"):
                if ub[k] + GRID_BOX_MARGIN < best:
                    break
                best = max(best, face(int(k), j, sign))
            if sign > 0:
                hi[j] = max(hi[j], best)
            else:
                lo[j] = min(lo[j], -best)
    return lo, hi


_OCTANT_BITS = ((np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1).astype(bool)  # (8, 3): octant o's signs


def _ball_lb(dbox, R, ig):
    """Lower bound of max_l g_l over a box at distance ``dbox`` (m) from a polytope's centre, from its
    bounding radius R (m) and 1/gamma ``ig``, with the outward cushion."""
    return (dbox * (1 - _CUSHION) - R) / ig - _CUSHION * (1.0 + dbox + R)


class _Geometry:
    """Plane rows of the scene and the per-box bounds of section 9 (float64, outward cushions)."""

    def __init__(self, packed: PackedScene, D: float, slack: float, eps: float, cut: float):
        self.pm = packed.plane_matrix().astype(np.float64)
        self.w1 = np.abs(self.pm[:, :3]).sum(axis=1)
        self.first = packed.polys["first"].astype(np.int64)
        self.count = packed.polys["count"].astype(np.int64)
        self.c, self.R, self.ig = _poly_geometry(packed)
        self.lead = packed.polys["lead"].astype(np.int64)  # (n, 8) lead plane per octant
        self.D, self.slack, self.eps = D, slack, eps
        self.cut = cut

    def listed(self, centres: np.ndarray, half: float, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((m, len(cand)) bool, (m, len(cand)) int): which candidate polytopes each box (centre, half side
        ``half`` grown by eps) must list, and how many of each one's half-planes can take the soft-max's
        expensive path there (a new maximum or an accumulated term, one exp each): g_l above the lead
        plane's minimum over the box minus the negligible cut (the running maximum is at least the lead's
        value).  U is taken over the candidates only (an upper bound all the same)."""
        return self.listed_many([(centres, half, cand)])[0]

    def listed_many(self, groups: list) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`listed` of each (centres, half, cand) of ``groups``, in one pass over all of them (the
        octree's splits: one call per split cost more in numpy's per-call overhead than in arithmetic).
        Bit for bit the values of one call per group: every value is computed by the same elementwise
        operations in the same order, the plane values g by one matrix product per group (the products'
        shapes are those of a single call), and the reductions are exact (max, min, integer sums) or over
        the same contiguous length-3 rows (the box distance).

        Layout: the groups' candidates, planes and boxes concatenated; the (box, plane) pairs of group p a
        block of m_p x P_p in row-major order, its (box, candidate) pairs a block of m_p x J_p."""
        out: list = [None] * len(groups)
        live = []
        for gi, (centres, _, cand) in enumerate(groups):
            if len(cand) == 0:
                out[gi] = (np.zeros((len(centres), 0), bool), np.zeros((len(centres), 0), np.int64))
            else:
                live.append(gi)
        if not live:
            return out
        cen_g = [np.asarray(groups[gi][0], np.float64).reshape(-1, 3) for gi in live]
        cand = np.concatenate([np.asarray(groups[gi][2], np.int64) for gi in live])
        hs = np.array([groups[gi][1] for gi in live], np.float64) + self.eps  # h per group, as half + eps
        m = np.array([len(c) for c in cen_g], np.int64)
        J = np.array([len(groups[gi][2]) for gi in live], np.int64)
        cnt = self.count[cand]
        cstart = np.cumsum(cnt) - cnt  # each candidate's first plane in the concatenated planes
        P = np.add.reduceat(cnt, np.r_[0, np.cumsum(J)[:-1]])  # planes per group
        pstart = np.cumsum(P) - P
        jstart = np.cumsum(J) - J
        mstart = np.cumsum(m) - m
        rows = np.repeat(self.first[cand] - cstart, cnt) + np.arange(int(cnt.sum()))
        pm = self.pm[rows]
        centres = np.concatenate(cen_g)
        # (box, plane) pairs: g from one product per group, the rest flat
        g = np.concatenate([(c @ pm[a:a + n, :3].T - pm[a:a + n, 3]).ravel()
                            for c, a, n in zip(cen_g, pstart.tolist(), P.tolist())])
        B = m * P
        bstart = np.cumsum(B) - B
        grp = np.repeat(np.arange(len(live)), B)
        local = np.arange(int(B.sum())) - bstart[grp]
        box = local // P[grp]
        plane = pstart[grp] + (local - box * P[grp])
        box += mstart[grp]
        hw = (np.repeat(hs, P) * self.w1[rows])[plane]
        tol = _CUSHION * (1.0 + np.abs(centres).sum(axis=1)[box] + np.abs(pm[:, 3])[plane])
        UBp = g + hw + tol
        LBp = g - hw - tol
        # (box, candidate) pairs: their planes are a contiguous run of each box's row
        C = m * J
        grp_c = np.repeat(np.arange(len(live)), C)
        local_c = np.arange(int(C.sum())) - (np.cumsum(C) - C)[grp_c]
        box_c = local_c // J[grp_c]
        kc = jstart[grp_c] + (local_c - box_c * J[grp_c])  # index into cand
        seg = bstart[grp_c] + box_c * P[grp_c] + (cstart[kc] - pstart[grp_c])
        box_c += mstart[grp_c]
        UB = np.maximum.reduceat(UBp, seg)
        LB = np.maximum.reduceat(LBp, seg)
        # the lead plane the kernel scans first is the one of the octant of p - c_k; over the box only
        # the octants whose signs occur there are possible
        ck = cand[kc]
        cen, cc, hc = centres[box_c], self.c[ck], hs[grp_c][:, None]
        pos = (cen + hc) >= cc  # u_i >= 0 possible
        neg = (cen - hc) <= cc  # u_i <= 0 possible
        # (pairs, 8): octant o possible over the box (-0.0 counts negative, as in the kernel)
        allowed = np.all(np.where(_OCTANT_BITS[None], neg[:, None, :], pos[:, None, :]), axis=2)
        lead_lb = np.where(allowed, LBp[seg[:, None] + self.lead[ck]], np.inf).min(axis=1)
        acc = np.add.reduceat((UBp > np.repeat(lead_lb - self.cut, cnt[kc])).astype(np.int64), seg)
        dbox = np.linalg.norm(np.maximum(np.abs(cen - cc) - hc, 0.0), axis=1)
        LB = np.maximum(LB, _ball_lb(dbox, self.R[ck], self.ig[ck]))
        # per box: min over its candidates (a contiguous run), capped at D
        per_box = np.repeat(J, m)
        thr = np.minimum(np.minimum.reduceat(UB, np.cumsum(per_box) - per_box), self.D) + self.slack
        lst = LB < np.repeat(thr, per_box)
        k = 0
        for gi, mi, Ji in zip(live, m.tolist(), J.tolist()):
            out[gi] = (lst[k:k + mi * Ji].reshape(mi, Ji), acc[k:k + mi * Ji].reshape(mi, Ji))
            k += mi * Ji
        return out

    def listed_grid(self, ijk: np.ndarray, centres: np.ndarray, half: float, block: int = 4):
        """:meth:`listed` of every top cell (integer cell ``ijk``, ``centres``, half side ``half``) against
        every polytope, as (m, n) arrays, the same values for the listed entries: blocks of ``block``^3 cells
        are evaluated against the polytopes :meth:`near_many` the block only (the top level cost grew with
        cells x half-planes: 75 of 112 s of the 150k-splat room's budget at 2.5 cm), many blocks per
        :meth:`listed_many` pass (about :data:`GRID_PAIRS_PER_PASS` (cell, half-plane) pairs each; one call per
        block cost more in numpy's per-call overhead than in arithmetic on small scenes)."""
        n = len(self.first)
        listed = np.zeros((len(centres), n), bool)
        accs = np.zeros((len(centres), n), np.int64)
        blk = ijk // block
        _, which = np.unique(blk, axis=0, return_inverse=True)
        order = np.argsort(which.ravel(), kind="stable")
        cuts = np.flatnonzero(np.diff(which.ravel()[order])) + 1
        starts = np.r_[0, cuts]
        lo = np.minimum.reduceat(centres[order], starts, axis=0) - half
        hi = np.maximum.reduceat(centres[order], starts, axis=0) + half
        near = self.near_many(lo, hi)
        groups, where, size = [], [], 0

        def flush():
            for (r, cand), (a, b) in zip(where, self.listed_many(groups)):
                listed[np.ix_(r, cand)] = a
                accs[np.ix_(r, cand)] = b
            groups.clear()
            where.clear()

        planes = np.r_[0, np.cumsum(self.count)]
        for rows, cand in zip(np.split(order, cuts), near):
            for i in range(0, len(rows), 2048):
                r = rows[i:i + 2048]
                groups.append((centres[r], half, cand))
                where.append((r, cand))
                size += len(r) * int(planes[cand + 1].sum() - planes[cand].sum())
                if size >= GRID_PAIRS_PER_PASS:
                    flush()
                    size = 0
        flush()
        return listed, accs

    def near_many(self, lo: np.ndarray, hi: np.ndarray, chunk: int = 1 << 20) -> list[np.ndarray]:
        """Per box [lo[b], hi[b]] ((B, 3) arrays, about ``chunk`` (box, polytope) pairs per pass): the polytopes
        whose ball bound (as in :meth:`listed`) over the box (grown by eps) is below D + slack. Every other one
        is listed by no box inside it (its lower bound there is at least as large, and its upper bound, at
        least its lower bound, cannot lower the threshold below D + slack)."""
        cen, half = (lo + hi) / 2, (hi - lo) / 2 + self.eps
        step = max(1, chunk // max(1, len(self.c)))
        out = []
        for i in range(0, len(lo), step):
            c, h = cen[i:i + step], half[i:i + step]
            dbox = np.linalg.norm(np.maximum(np.abs(c[:, None, :] - self.c[None]) - h[:, None, :], 0.0), axis=2)
            ok = _ball_lb(dbox, self.R[None], self.ig[None]) < self.D + self.slack
            out += [np.flatnonzero(row) for row in ok]
        return out


def leaf_work(packed: PackedScene, kappa: float = 100.0) -> np.ndarray:
    """(leaves, 5) int: list id, depth, listed polytopes, their half-planes and the half-planes that can
    take the expensive soft-max path, for every non-empty leaf box of the index (recomputed from the
    tree when the index was not built in this process; ``kappa`` the build kappa)."""
    ix = packed.index
    if ix.work is not None and (ix.kappa is None or ix.kappa == kappa):
        return ix.work
    D = float(ix.cap)
    lo = np.asarray(ix.origin, np.float64)
    dims = np.array(ix.dims)
    extent = float(np.max(np.abs(np.r_[lo, lo + dims * ix.cell]))) + 2.0 * max(ix.cell, float(np.max(dims * ix.cell)))
    geo = _Geometry(packed, D, index_slack(packed, kappa), lookup_eps(extent), NEGLIGIBLE_NATS / kappa)
    lists = ix.lists()
    offs = np.array([[(o >> b) & 1 for b in range(3)] for o in range(8)], np.float64) - 0.5
    out, boxes = [], []
    todo = []
    nx, ny, _ = ix.dims
    for c, v in enumerate(ix.cell_list.astype(np.int64)):
        ijk = np.array([c % nx, (c // nx) % ny, c // (nx * ny)])
        todo.append((int(v), lo + (ijk + 0.5) * ix.cell, 0.5 * ix.cell, 0))
    while todo:
        v, cen, half, depth = todo.pop()
        if v >= ix.n_lists:
            b = v - ix.n_lists
            for o in range(8):
                todo.append((int(ix.children[8 * b + o]), cen + offs[o] * half, half / 2, depth + 1))
            continue
        lst = lists[v].astype(np.int64)
        if len(lst) == 0:
            continue
        out.append([v, depth, len(lst), int(geo.count[lst].sum()), 0])
        boxes.append((cen[None], half, lst))
    for k in range(0, len(boxes), 256):  # the leaves' expensive planes, many leaves per pass
        for row, (_, acc) in zip(out[k:k + 256], geo.listed_many(boxes[k:k + 256])):
            row[4] = int(acc.sum())
    return np.array(out, np.int64).reshape(-1, 5)


def index_slack(packed: PackedScene, kappa: float) -> float:
    """The tightness slack (17 + log L_max) / kappa of section 4, metres."""
    return (NEGLIGIBLE_NATS + float(packed.log_lmax)) / kappa


def top_grid(box: tuple, cell: float, max_cells: int = 65535) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(origin, dims, cell, eps) of the top grid :func:`build_index` lays over ``box`` = :func:`grid_box`
    with top cells of ``cell`` metres: doubled while the grid would have more than ``max_cells`` cells
    (a large box B, sharp polytopes grown far by delta, gets larger top cells: they are cheap)."""
    lo, hi = np.array(box[0], np.float64), np.array(box[1], np.float64)
    extent = float(np.max(np.abs(np.r_[lo, hi]))) + 2.0 * max(cell, float(np.max(hi - lo)))
    eps = lookup_eps(extent)
    lo, hi = lo - 2 * eps, hi + 2 * eps
    while True:
        origin = np.floor(lo / cell) * cell
        dims = np.maximum(1, np.ceil((hi - origin) / cell).astype(np.int64))
        if np.all(dims <= 65535) and int(np.prod(dims)) <= max_cells:
            return origin, dims, cell, eps
        cell *= 2.0


def index_bytes_at_least(box: tuple, cell: float, n_polys: int, max_cells: int = 65535) -> int:
    """A lower bound on :meth:`SceneIndex.nbytes` of any index :func:`build_index` makes over ``box`` with top
    cells of ``cell`` metres, whatever its lists and refinement: its top cells, no inner node, one list, no
    entry. A caller with fewer bytes than this need not list the top grid (the costly part) to know it
    cannot fit."""
    dims = top_grid(box, cell, max_cells)[1]
    return index_bytes(int(np.prod(dims)), 0, 0, 0, n_polys)


def build_index(packed: PackedScene, cap: float = DEFAULT_CLEARANCE_CAP, cell: float = 1.0, kappa: float = 100.0,
                target: float | None = None, max_bytes: int | None = None, cost=None, max_depth: int = 4,
                max_cells: int = 65535, box: tuple | None = None) -> SceneIndex:
    """The grid index of ``packed`` with clearance cap ``cap`` (D, metres) and top cell size ``cell``
    (a power of two, metres); the tightness slack is (17 + log L_max) / kappa.

    Refinement: the leaf with the largest ``cost(polys, planes)`` (default a proxy of the cycle model;
    the budget passes the model itself, depth included) is split into its 8 octants, up to
    ``max_depth`` levels, until the largest cost is at most ``target`` or the index would exceed
    ``max_bytes`` (None: no such limit; target None: refine as long as the worst leaf can be split
    within the bytes).  ``box`` is :func:`grid_box` (packed, D + slack) if the caller has it."""
    import heapq

    if cell <= 0 or math.log2(cell) != int(math.log2(cell)):
        raise PolyccError(f"index cell size {cell} must be a power of two (metres)")
    if not cap > 0:
        raise PolyccError(f"--clearance-cap must be positive (got {cap})")
    n = packed.n_polys
    if n == 0:
        raise PolyccError("an index needs at least one polytope")
    if packed.n_planes > 65535:
        raise PolyccError("the index stores uint16 first-plane indices: at most 65535 half-planes")
    if cost is None:  # a proxy of the cycle model (polycc.budget.cycle_model.indexed_cycles), in Python floats
        def cost(m, planes, depth, acc):
            return 250.0 * m + 70.0 * planes + 120.0 * acc
    D = float(np.float32(cap))
    slack = index_slack(packed, kappa)
    box = box if box is not None else grid_box(packed, D + slack)
    origin, dims, cell, eps = top_grid(box, cell, max_cells)
    nx, ny, nz = (int(v) for v in dims)
    ii, jj, kk = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    idx = np.stack([ii.ravel(order="F"), jj.ravel(order="F"), kk.ravel(order="F")], axis=1)  # i fastest
    centres = origin + (idx + 0.5) * cell
    geo = _Geometry(packed, D, slack, eps, NEGLIGIBLE_NATS / kappa)
    listed, accs = geo.listed_grid(idx, centres, 0.5 * cell)
    count = geo.count
    # nodes: [centre, half, depth, list (polytope indices) or None, children or None, expensive planes,
    #         half-planes of the list, the list's key]
    planes0 = listed.astype(np.int64) @ count
    acc0 = (accs * listed).sum(axis=1)
    nodes = []
    cols, ends = np.nonzero(listed)[1], np.cumsum(listed.sum(axis=1))
    lsts = [cols[a:b] for a, b in zip((ends - listed.sum(axis=1)).tolist(), ends.tolist())]  # np.nonzero(row)
    for i, lst in enumerate(lsts):
        nodes.append([centres[i], 0.5 * cell, 0, lst, None, int(acc0[i]), int(planes0[i]), lst.tobytes()])
    refs: dict[bytes, int] = {}
    for nd in nodes:
        refs[nd[7]] = refs.get(nd[7], 0) + 1
    entries = sum(len(k) // 8 for k in refs)

    def nbytes(n_inner):
        return index_bytes(len(centres), n_inner, len(refs), entries, n)

    def node_cost(nd):
        return float(cost(len(nd[3]), nd[6], nd[2], nd[5]))

    heap = [(-node_cost(nd), i) for i, nd in enumerate(nodes) if len(nd[3])]
    heapq.heapify(heap)
    n_inner = 0
    offs = np.array([[(o >> b) & 1 for b in range(3)] for o in range(8)], np.float64) - 0.5
    # The children of the leaves at the top of the heap are listed ahead, several splits per numpy pass
    # (a leaf's children depend on that leaf alone, so the index is the same); the batch doubles up to
    # SPLIT_BATCH_MAX as splits go on, so a refinement that stops early computes at most as many unused.
    ahead: dict[int, tuple] = {}
    batch = min(4, SPLIT_BATCH_MAX)
    while heap:
        c0, i = heap[0]
        nd = nodes[i]
        if target is not None and -c0 <= target:
            break
        if nd[2] >= max_depth:
            break  # the worst leaf cannot be split: the worst case stays
        half = nd[1] / 2
        kc = nd[0] + offs * nd[1]  # child centres (octant o: bit set = upper half)
        if i not in ahead:
            top = [heapq.heappop(heap) for _ in range(min(batch, len(heap)))]  # keys are unique: the heap's
            for e in top:  # later pops do not depend on its internal order
                heapq.heappush(heap, e)
            todo = [j for _, j in top if j not in ahead and nodes[j][2] < max_depth]
            res = geo.listed_many([(nodes[j][0] + offs * nodes[j][1], nodes[j][1] / 2, nodes[j][3]) for j in todo])
            ahead.update(zip(todo, res))
            batch = min(2 * batch, SPLIT_BATCH_MAX)
        sub, sub_acc = ahead.pop(i)
        kids = [nd[3][sub[o]] for o in range(8)]
        kid_keys = [kl.tobytes() for kl in kids]
        kid_acc = (sub_acc * sub).sum(axis=1).tolist()
        kid_planes = (sub.astype(np.int64) @ count[nd[3]]).tolist()
        # bytes after the split: the changed reference counts only (refs is not copied per split)
        delta = {nd[7]: -1}
        for kk_ in kid_keys:
            delta[kk_] = delta.get(kk_, 0) + 1
        new_len, new_entries = len(refs), entries
        for kk_, d in delta.items():
            old = refs.get(kk_, 0)
            if old == 0 and old + d > 0:
                new_len += 1
                new_entries += len(kk_) // 8
            elif old > 0 and old + d == 0:
                new_len -= 1
                new_entries -= len(kk_) // 8
        if new_len + n_inner + 1 > 65535 or new_entries > 65535 or (
                max_bytes is not None and index_bytes(len(centres), n_inner + 1, new_len, new_entries, n)
                > max_bytes):
            break
        heapq.heappop(heap)
        for kk_, d in delta.items():
            v = refs.get(kk_, 0) + d
            if v:
                refs[kk_] = v
            else:
                del refs[kk_]
        entries = new_entries
        n_inner += 1
        nd[4] = []
        for o in range(8):
            child = [kc[o], half, nd[2] + 1, kids[o], None, kid_acc[o], kid_planes[o], kid_keys[o]]
            nd[4].append(len(nodes))
            nodes.append(child)
            if len(kids[o]):
                heapq.heappush(heap, (-node_cost(child), len(nodes) - 1))
        nd[3] = None
    # ids: lists first (empty list first, then by length), internal nodes after them
    lists = sorted((np.frombuffer(k, np.int64) for k in refs), key=lambda x: (len(x), x.tolist()))
    lid = {x.tobytes(): j for j, x in enumerate(lists)}
    inner = [i for i, nd in enumerate(nodes) if nd[4] is not None]
    nid = {i: len(lists) + j for j, i in enumerate(inner)}

    def ref(i):
        nd = nodes[i]
        return nid[i] if nd[4] is not None else lid[nd[7]]

    cell_list = np.array([ref(i) for i in range(len(centres))], np.uint16)
    children = np.array([ref(c) for i in inner for c in nodes[i][4]], np.uint16)
    starts = np.r_[0, np.cumsum([len(x) for x in lists])].astype(np.uint16)
    ent = np.concatenate(lists).astype(np.uint16) if len(lists) and starts[-1] else np.zeros(0, np.uint16)
    work = np.array([[lid[nd[7]], nd[2], len(nd[3]), nd[6], nd[5]] for nd in nodes
                     if nd[4] is None and len(nd[3])], np.int64).reshape(-1, 5)
    out = SceneIndex(np.asarray(origin, np.float32), float(cell), (nx, ny, nz), np.float32(D), cell_list,
                     starts, ent, geo.first.astype(np.uint16), float(kappa), children, work)
    assert out.nbytes() == nbytes(n_inner)
    return out
