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
from polycc.onboard.layout import PackedScene, SceneIndex

DEFAULT_CLEARANCE_CAP = 0.6  # m
DEFAULT_CELLS = (0.25, 0.5, 1.0)  # cell sizes s (powers of two, metres) tried by choose_index
NEGLIGIBLE_NATS = 17.0
_CUSHION = 1e-9  # relative outward cushion of the float64 geometry (errors are ~1e-15 relative)




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

    from scipy.optimize import linprog

    res = linprog(-e, A_ub=n, b_ub=d + delta, bounds=[(None, None)] * 3, method="highs")
    if res.status != 0:
        raise PolyccError("index: the grid box LP failed (an unbounded polytope?)")
    lam = np.maximum(-np.asarray(res.ineqlin.marginals, np.float64), 0.0)
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


def grid_box(packed: PackedScene, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) such that every polytope has phi_k(p) >= delta at every p outside [lo, hi]
    (certified per face by :func:`_face_bound`): the union of the polytopes grown by delta, boxed."""
    pm = packed.plane_matrix().astype(np.float64)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for p in packed.polys:
        rows = pm[int(p["first"]) : int(p["first"]) + int(p["count"])]
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1.0
            hi[j] = max(hi[j], _face_bound(rows[:, :3], rows[:, 3], e, delta))
            lo[j] = min(lo[j], -_face_bound(rows[:, :3], rows[:, 3], -e, delta))
    return lo, hi


def build_index(packed: PackedScene, cap: float = DEFAULT_CLEARANCE_CAP, cell: float = 0.5, kappa: float = 100.0,
                max_cells: int = 65535) -> SceneIndex:
    """The grid index of ``packed`` with clearance cap ``cap`` (D, metres) and cell size ``cell``
    (a power of two, metres); the tightness slack is (17 + log L_max) / kappa."""
    if cell <= 0 or math.log2(cell) != int(math.log2(cell)):
        raise PolyccError(f"index cell size {cell} must be a power of two (metres)")
    if not cap > 0:
        raise PolyccError(f"--clearance-cap must be positive (got {cap})")
    n = packed.n_polys
    if n == 0:
        raise PolyccError("an index needs at least one polytope")
    if packed.n_planes > 65535:
        raise PolyccError("the index stores uint16 first-plane indices: at most 65535 half-planes")
    D = float(np.float32(cap))
    slack = (NEGLIGIBLE_NATS + float(packed.log_lmax)) / kappa
    c, R, ig = _poly_geometry(packed)
    lo, hi = grid_box(packed, D + slack)
    extent = float(np.max(np.abs(np.r_[lo, hi]))) + cell
    eps = lookup_eps(extent)
    lo, hi = lo - 2 * eps, hi + 2 * eps
    origin = np.floor(lo / cell) * cell
    dims = np.maximum(1, np.ceil((hi - origin) / cell).astype(np.int64))
    if np.any(dims > 65535) or int(np.prod(dims)) > max_cells:
        raise PolyccError(f"index grid {dims.tolist()} at {cell} m exceeds {max_cells} cells; use larger cells")
    nx, ny, nz = (int(v) for v in dims)
    # cell centres, i fastest
    ii, jj, kk = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    idx = np.stack([ii.ravel(order="F"), jj.ravel(order="F"), kk.ravel(order="F")], axis=1)
    centres = origin + (idx + 0.5) * cell
    h = 0.5 * cell + eps
    pm = packed.plane_matrix().astype(np.float64)
    w1 = np.abs(pm[:, :3]).sum(axis=1)
    first = packed.polys["first"].astype(np.int64)
    count = packed.polys["count"].astype(np.int64)
    m = len(centres)
    LB = np.empty((m, n))
    UB = np.empty((m, n))
    for k in range(n):
        rows = slice(first[k], first[k] + count[k])
        g = centres @ pm[rows, :3].T - pm[rows, 3]  # (m, L)
        tol = _CUSHION * (1.0 + np.abs(centres).sum(axis=1)[:, None] + np.abs(pm[rows, 3])[None, :])
        UB[:, k] = np.max(g + h * w1[rows] + tol, axis=1)
        lb_planes = np.max(g - h * w1[rows] - tol, axis=1)
        dbox = np.linalg.norm(np.maximum(np.abs(centres - c[k]) - h, 0.0), axis=1)
        lb_ball = (dbox * (1 - _CUSHION) - R[k]) / ig[k] - _CUSHION * (1.0 + dbox + R[k])
        LB[:, k] = np.maximum(lb_planes, lb_ball)
    U = UB.min(axis=1)
    thr = np.minimum(U, D) + slack
    listed = LB < thr[:, None]
    # unique lists (cells far from everything share the empty list)
    keys = np.packbits(listed, axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    lists = [np.nonzero(np.unpackbits(u)[:n])[0] for u in uniq]
    order = sorted(range(len(lists)), key=lambda i: (len(lists[i]), lists[i].tolist()))  # empty list first
    rank = np.empty(len(lists), np.int64)
    rank[order] = np.arange(len(lists))
    lists = [lists[i] for i in order]
    starts = np.r_[0, np.cumsum([len(x) for x in lists])]
    if starts[-1] > 10**9 or len(lists) > 65534 and False:
        raise PolyccError(f"index of {starts[-1]} entries / {len(lists)} lists exceeds uint16; use larger cells")
    entries = np.concatenate(lists).astype(np.uint16) if starts[-1] else np.zeros(0, np.uint16)
    cell_list = rank[inv].astype(np.uint16)
    return SceneIndex(np.asarray(origin, np.float32), float(cell), (nx, ny, nz), np.float32(D), cell_list,
                      starts.astype(np.uint16), entries, first.astype(np.uint16), float(kappa))
