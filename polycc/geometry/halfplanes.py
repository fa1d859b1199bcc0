"""Convex polytopes in half-plane form, world frame, metres: ``P = {p : n_l . p <= d_l}``.

Rows are ``[nx, ny, nz, d]`` (float64 here). Each primitive exists once:

* :func:`is_bounded` -- P is bounded iff the normals positively span R^3, i.e. the origin is
  strictly inside their convex hull (qhull's half-space intersection does not detect an
  unbounded intersection reliably, so this is checked separately). ``min_gamma`` is the
  required depth of the origin in the hull of the unit normals (gamma = min_{|u|=1} max_l
  n_l . u); a positive margin also rules out needle-like polytopes.
* :func:`chebyshev_centre` -- centre and radius of the largest ball in P (HiGHS LP).
* :func:`polytope_vertices` -- vertices by half-space intersection (qhull), or None;
  :func:`polytope_vertices_volume` -- the same and the volume, from the same qhull run.
* :func:`inv_gamma` -- 1/gamma of a set of normals (the culling factor of the on-board layout).
* :func:`hull_halfplanes`, :func:`axis_box` -- half-planes of a convex hull of points / of a box.

``polycc.verify`` keeps its own independent copy of vertex enumeration on purpose.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from polycc.errors import PolyccError
from polycc.geometry.lp_raw import linprog_highs
from polycc.geometry.qhull_raw import halfspaces_raw

MIN_PLANES = 4  # a bounded polytope in R^3 needs at least 4 half-planes
_AXES = np.arange(3)


def is_bounded(normals: np.ndarray, min_gamma: float = 1e-9) -> bool:
    """True if ``{p : n_l . p <= d_l}`` is bounded for any offsets (see module docstring)."""
    n = np.asarray(normals, np.float64)
    if len(n) < MIN_PLANES:
        return False
    norms = np.linalg.norm(n, axis=1, keepdims=True)
    if np.any(norms == 0):
        return False
    try:
        eq = ConvexHull(n / norms).equations
    except (QhullError, ValueError):  # fewer than 4 distinct or all in a plane: cannot surround the origin
        return False
    return bool(np.all(eq[:, 3] < -min_gamma))


def chebyshev_centre(h: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and radius of the largest ball inside ``{n . p <= d}`` (float64 LP); PolyccError if
    the polytope is empty, flat or unbounded."""
    h = np.asarray(h, np.float64)
    n, d = h[:, :3], h[:, 3]
    norms = np.linalg.norm(n, axis=1)
    # linprog(c=[0, 0, 0, -1], A_ub=[n, |n|], b_ub=d, bounds x, y, z free, r >= 0, method="highs"), bit for bit
    status, x, _ = linprog_highs(_CHEB_COST, np.c_[n, norms], d, _CHEB_LB, _CHEB_UB)
    if status != 0 or x[3] <= 0:
        raise PolyccError("a polytope is empty, flat or unbounded; every polytope needs a non-empty interior")
    return x[:3], float(x[3])


_CHEB_COST = np.array([0.0, 0.0, 0.0, -1.0])
_CHEB_LB = np.array([-np.inf, -np.inf, -np.inf, 0.0])
_CHEB_UB = np.full(4, np.inf)


def _intersection(h: np.ndarray, interior, min_gamma: float, max_reach: float):
    """qhull's half-space intersection of ``{n . p <= d}`` and the interior point used, or None."""
    h = np.asarray(h, np.float64)
    if interior is not None:
        r = _intersection_certified(h, np.asarray(interior, np.float64), min_gamma, max_reach)
        if r is not False:
            return r
    if not is_bounded(h[:, :3], min_gamma):
        return None
    if interior is None:
        try:
            interior, _ = chebyshev_centre(h)
        except PolyccError:
            return None
    interior = np.asarray(interior, np.float64)
    try:
        with np.errstate(divide="ignore", invalid="ignore"):
            hs = halfspaces_raw(np.c_[h[:, :3], -h[:, 3]], interior)
    except (QhullError, ValueError):
        return None
    v = hs.intersections
    if len(v) == 0 or not np.all(np.isfinite(v)) or np.abs(v - interior).max() > max_reach:
        return None
    return hs, interior


GAMMA_SAFETY = 2.0  # the certified bound must beat min_gamma by this factor (qhull's rounding is ~1e-15)


def _intersection_certified(h: np.ndarray, c: np.ndarray, min_gamma: float, max_reach: float):
    """:func:`_intersection` without the separate :func:`is_bounded` hull when the intersection itself
    proves it (the result is then the same); False when it does not, and the caller runs both.

    With ``c`` strictly inside, the polytope is bounded iff the origin is strictly inside qhull's dual hull
    (of the points ``n_l / h_l``, ``h_l = d_l - n_l . c`` for unit ``n_l``, which positively span R^3 iff
    the normals do). Then every vertex lies within ``R = max |v - c|`` of ``c``, and for any unit u the
    point ``c + R' u`` (R' > R) is outside, so some ``n_l . u > h_l / R'``: gamma >= min_l h_l / R. When
    that bound clears ``min_gamma`` (by :data:`GAMMA_SAFETY`), :func:`is_bounded` is True and qhull's
    intersection from ``c`` is the one it would compute next. Saves a third of a drop cost."""
    if len(h) < MIN_PLANES:
        return False
    n = h[:, :3]
    norms = np.sqrt(np.add.reduce(n * n, axis=1))  # np.linalg.norm(n, axis=1), without its checks
    if not norms.min() > 0:
        return False
    depth = (h[:, 3] - n @ c) / norms
    if not depth.min() > 0:
        return False
    try:
        with np.errstate(divide="ignore", invalid="ignore"):
            hs = halfspaces_raw(np.concatenate([n, -h[:, 3:]], axis=1), c)
    except (QhullError, ValueError):
        return False
    if not hs.dual_equations[:, 3].max() < 0:
        return False
    v = hs.intersections
    if len(v) == 0 or not np.all(np.isfinite(v)):
        return False
    radius = float(np.sqrt(((v - c) ** 2).sum(axis=1).max()))
    if not depth.min() >= GAMMA_SAFETY * min_gamma * radius:
        return False
    return None if np.abs(v - c).max() > max_reach else (hs, c)


def polytope_vertices(h: np.ndarray, interior: np.ndarray | None = None, min_gamma: float = 1e-9,
                      max_reach: float = 1e6) -> np.ndarray | None:
    """Vertices of ``{n . p <= d}`` (rows ``[n, d]``), or None if it is unbounded or degenerate.

    ``interior`` is a strictly interior point (default: the Chebyshev centre). Vertices farther
    than ``max_reach`` metres from it count as unbounded."""
    r = _intersection(h, interior, min_gamma, max_reach)
    return None if r is None else r[0].intersections


def polytope_vertices_volume(h: np.ndarray, interior: np.ndarray | None = None, min_gamma: float = 1e-9,
                             max_reach: float = 1e6) -> tuple[np.ndarray, float] | None:
    """(vertices, volume m^3) of ``{n . p <= d}``, or None as :func:`polytope_vertices`.

    The volume comes from the same qhull run, not a second hull of the vertices (which cost 3-4x the
    intersection on the 100-300-plane polytopes of a 2.5 cm build). Each facet of qhull's dual hull is a
    vertex and lists the planes it lies on, so each plane p lists the vertices of its face. Ordered by
    angle around their mean g_p (a convex face), they give the face's area A_p by the shoelace formula,
    and V = sum_p A_p h_p / 3, h_p the distance of plane p from the interior point. Falls back to the
    hull of the vertices if fewer than four faces have an area."""
    r = _intersection(h, interior, min_gamma, max_reach)
    if r is None:
        return None
    hs, c = r
    v = hs.intersections
    vol = _dual_volume(hs.dual_facets, v, c, np.asarray(h, np.float64))
    return v, (polytope_volume(v) if vol is None else vol)


def _dual_volume(facets, v: np.ndarray, c: np.ndarray, planes: np.ndarray) -> float | None:
    """Volume from qhull's dual (see :func:`polytope_vertices_volume`), None if a face is degenerate.

    When every vertex lies on exactly three planes (qhull's dual facets are triangles, the usual case),
    each pair of planes of a vertex is an edge of the polytope shared by exactly two vertices, and the
    pyramid over each face is a fan of tetrahedra (c, face mean, edge): no angular sort. Otherwise
    :func:`_dual_volume_sorted`."""
    try:
        f = np.asarray(facets, np.int64)
    except ValueError:  # a vertex on four or more planes: faces in angular order instead
        return _dual_volume_sorted(facets, v, c, planes)
    if f.ndim != 2 or f.shape[1] != 3:
        return _dual_volume_sorted(facets, v, c, planes)
    m, n_planes = len(f), len(planes)
    w = v - c
    p = f.ravel()
    cnt = np.bincount(p, minlength=n_planes)
    if np.count_nonzero(cnt >= 3) < MIN_PLANES:
        return None
    # face means relative to c: one bincount over (plane, axis) bins, each bin summed in the same order as
    # a bincount per axis would
    g = np.bincount((p[:, None] * 3 + _AXES).ravel(), weights=np.repeat(w, 3, axis=0).ravel(),
                    minlength=3 * n_planes).reshape(n_planes, 3)
    g /= np.maximum(cnt, 1)[:, None]
    fs = np.sort(f, axis=1)
    a, b, d = fs[:, 0] * n_planes, fs[:, 1], fs[:, 2]
    key = np.concatenate([a + b, a + d, b * n_planes + d])  # the edges (plane pairs) at each vertex
    order = np.argsort(key, kind="stable")
    if len(order) % 2:
        return _dual_volume_sorted(facets, v, c, planes)
    e0, e1 = order[0::2], order[1::2]
    edge = key[e0]
    if not np.array_equal(edge, key[e1]):  # not a closed triangulated surface: the general way
        return _dual_volume_sorted(facets, v, c, planes)
    cr = _cross(w[e0 % m], w[e1 % m])
    q, r = np.divmod(edge, n_planes)
    vol = np.abs(np.einsum("ij,ij->i", g[q], cr)).sum() + np.abs(np.einsum("ij,ij->i", g[r], cr)).sum()
    return float(vol / 6.0)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two (N, 3) arrays, the same products and differences, without its axis handling."""
    x, y = a.T, b.T
    cr = np.empty((len(a), 3))
    cr[:, 0] = x[1] * y[2] - x[2] * y[1]
    cr[:, 1] = x[2] * y[0] - x[0] * y[2]
    cr[:, 2] = x[0] * y[1] - x[1] * y[0]
    return cr


def _norms(a: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(a, axis=1, keepdims=True)`` of a real (N, 3) array, the same sums."""
    return np.sqrt(np.add.reduce(a * a, axis=1, keepdims=True))


def _dual_volume_sorted(facets, v: np.ndarray, c: np.ndarray, planes: np.ndarray) -> float | None:
    """Volume from qhull's dual (see :func:`polytope_vertices_volume`), None if a face is degenerate."""
    if not len(facets):
        return None
    sizes = np.fromiter((len(f) for f in facets), np.int64, len(facets))
    p = np.fromiter(itertools.chain.from_iterable(facets), np.int64, int(sizes.sum()))
    i = np.repeat(np.arange(len(facets)), sizes)  # incidence (vertex i lies on plane p)
    n_planes = len(planes)
    w = v - c
    if np.count_nonzero(np.bincount(p, minlength=n_planes) >= 3) < MIN_PLANES:
        return None
    n = planes[:, :3] / _norms(planes[:, :3])
    area, g = _face_areas(w[i], p, n, n_planes)  # face means relative to c
    height = np.einsum("ij,ij->i", g, n)  # distance of each face's plane from c (g lies on the face)
    return float((area * height).sum() / 3.0)


def _face_areas(pts: np.ndarray, face: np.ndarray, n: np.ndarray, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """(area, mean) of each convex face polygon: ``pts`` (K, 3) its vertices in any order (repeats add nothing),
    ``face`` (K,) the face each lies on, ``n`` (n_faces, 3) the faces' unit normals. Each face's vertices are
    put in angular order around their mean in the face's plane and summed by the shoelace formula."""
    cnt = np.bincount(face, minlength=n_faces).astype(np.float64)
    g = np.bincount((face[:, None] * 3 + _AXES).ravel(), weights=pts.ravel(),
                    minlength=3 * n_faces).reshape(n_faces, 3)
    g /= np.maximum(cnt, 1.0)[:, None]
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = _cross(n, np.broadcast_to(helper, n.shape))
    e1 /= _norms(e1)
    e2 = _cross(n, e1)
    r = pts - g[face]
    x = np.einsum("ij,ij->i", r, e1[face])
    y = np.einsum("ij,ij->i", r, e2[face])
    order = np.lexsort((np.arctan2(y, x), face))  # each face's vertices in angular order around its mean
    p, x, y = face[order], x[order], y[order]
    start = np.concatenate([[0], np.flatnonzero(np.diff(p)) + 1])
    nxt = np.arange(1, len(p) + 1)
    nxt[np.concatenate([start[1:], [len(p)]]) - 1] = start  # the last vertex of a face is followed by its first
    cross = x * y[nxt] - x[nxt] * y
    return np.bincount(p, weights=cross, minlength=n_faces) * 0.5, g


TRIPLE_PLANES_MAX = 64  # drop_volumes enumerates plane triples up to this many planes, qhull per plane above
_TRIPLES: dict = {}
# directions whose closest normals pre-screen the triples of _cap_volumes (the cube's 6 faces and 8 corners)
_PROBE = np.concatenate([np.eye(3), -np.eye(3),
                         np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / np.sqrt(3.0)])


def _triples(m: int) -> np.ndarray:
    """(C(m, 3), 3) int64: every triple i < j < k of range(m), lexicographic (cached per m)."""
    t = _TRIPLES.get(m)
    if t is None:
        i, j, k = np.meshgrid(np.arange(m), np.arange(m), np.arange(m), indexing="ij")
        sel = (i < j) & (j < k)
        t = _TRIPLES[m] = np.column_stack([i[sel], j[sel], k[sel]]).astype(np.int64)
    return t


def bounded_without(normals: np.ndarray, min_gamma: float = 1e-9) -> np.ndarray:
    """(m,) bool: ``is_bounded(normals without row j, min_gamma)`` for every j.

    Most rows are certified at once: a subset S of the normals that is bounded with twice the margin stays
    bounded in every superset (the hull of a superset contains the hull of S, so the origin lies at least as
    deep), so every j outside S is True. S is the normal closest to each of the six axis directions; a second
    such S' from the other rows certifies the rows of S the same way. Rows left uncertified get the exact
    :func:`is_bounded` of the other rows."""
    n = np.asarray(normals, np.float64)
    m = len(n)
    out = np.zeros(m, bool)
    if m <= MIN_PLANES:
        return out
    u = n / _norms(n)
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    free = np.ones(m, bool)
    certs = []
    for _ in range(2):
        if free.sum() < MIN_PLANES:
            break
        score = np.where(free[None, :], axes @ u.T, -np.inf)
        s = np.unique(score.argmax(axis=1))
        if len(s) < MIN_PLANES or not is_bounded(n[s], GAMMA_SAFETY * min_gamma):
            break
        certs.append(s)
        free[s] = False
    if not certs:
        return np.array([is_bounded(np.delete(n, j, axis=0), min_gamma) for j in range(m)])
    out[:] = True
    left = certs[0] if len(certs) == 1 else np.zeros(0, np.int64)  # rows of S no S' certifies
    for j in left:
        out[j] = is_bounded(np.delete(n, j, axis=0), min_gamma)
    return out


def drop_volume(h: np.ndarray, j: int, interior: np.ndarray, volume: float, min_gamma: float = 1e-9) -> float:
    """Volume (m^3) that dropping plane j adds to ``{n . p <= d}`` of volume ``volume``, inf if the other planes
    are not bounded with margin ``min_gamma``: one qhull half-space intersection from ``interior``."""
    r = polytope_vertices_volume(np.concatenate((h[:j], h[j + 1:])), interior, min_gamma)  # np.delete, faster
    return np.inf if r is None else max(r[1] - volume, 0.0)


def drop_volumes(h: np.ndarray, min_gamma: float = 1e-9, interior: np.ndarray | None = None,
                 volume: float | None = None) -> np.ndarray:
    """(m,) volume (m^3) that dropping each half-plane adds to the bounded polytope ``{n . p <= d}``, inf
    where the other planes are not bounded with margin ``min_gamma`` (:func:`bounded_without`).

    Up to :data:`TRIPLE_PLANES_MAX` planes, every plane at once from one enumeration of plane triples
    (numpy, no qhull): a triple's point that violates no plane is a vertex of P, one that violates only plane
    j a vertex of the cap ``C_j`` = (P without j) minus P beyond plane j. The cap's vertices are those and P's
    vertices on plane j; its volume is the sum over its faces on the other planes of area x height / 3 from
    an apex on plane j (the mean of P's vertices there), each face's area by the shoelace formula around its
    mean. Above that many planes (the enumeration grows as m^4), one qhull half-space intersection per plane
    (:func:`polytope_vertices_volume` from ``interior``, less ``volume``). Degenerate vertices (more than
    three planes, or the outward margin's slivers) repeat points within the tolerance: repeated points add
    nothing to a shoelace sum."""
    h = np.asarray(h, np.float64)
    m = len(h)
    ok = bounded_without(h[:, :3], min_gamma)
    out = np.full(m, np.inf)
    if not ok.any():
        return out
    if m > TRIPLE_PLANES_MAX:
        c = np.asarray(interior if interior is not None else chebyshev_centre(h)[0], np.float64)
        vol = float(volume) if volume is not None else polytope_volume(polytope_vertices(h, c, min_gamma))
        for j in np.flatnonzero(ok):
            out[j] = drop_volume(h, int(j), c, vol, min_gamma)
        return out
    out[ok] = _cap_volumes(h)[ok]
    return out


def _cap_volumes(h: np.ndarray) -> np.ndarray:
    """Volume of each cap C_j of :func:`drop_volumes` by triple enumeration (no boundedness check)."""
    m = len(h)
    nn = _norms(h[:, :3])[:, 0]
    n = h[:, :3] / nn[:, None]
    d = h[:, 3] / nn
    t = _triples(m)
    a, b, c = n[t[:, 0]], n[t[:, 1]], n[t[:, 2]]
    bc, ca, ab = _cross(b, c), _cross(c, a), _cross(a, b)
    det = np.einsum("ij,ij->i", a, bc)
    good = np.abs(det) > 1e-12
    t, det, bc, ca, ab = t[good], det[good], bc[good], ca[good], ab[good]
    p = (d[t[:, 0], None] * bc + d[t[:, 1], None] * ca + d[t[:, 2], None] * ab) / det[:, None]
    tol = 1e-9 * max(1.0, float(np.abs(d).max()))
    # most triples' points lie beyond several planes: a few planes reject them before the full test
    probe = _PROBE @ n.T
    few = np.unique(probe.argmax(axis=1))
    maybe = np.count_nonzero(p @ n[few].T - d[few] > tol, axis=1) <= 1
    p = p[maybe]
    s = p @ n.T - d  # (T', m) signed distances
    viol = s > tol
    nv = np.count_nonzero(viol, axis=1)
    keep = nv <= 1
    p, s, viol, nv = p[keep], s[keep], viol[keep], nv[keep]
    on = np.abs(s) <= tol
    vj = np.where(nv == 1, viol.argmax(axis=1), -1)
    out = np.zeros(m)
    new = np.flatnonzero(vj >= 0)
    if not len(new):
        return out
    base = np.flatnonzero(vj < 0)
    kb, jb = np.nonzero(on[base])  # P's vertex base[kb] lies on plane jb: in the base of C_jb
    kb = base[kb]
    cnt = np.bincount(jb, minlength=m)
    apex = np.stack([np.bincount(jb, weights=p[kb, ax], minlength=m) for ax in range(3)], axis=1)
    apex /= np.maximum(cnt, 1)[:, None]
    kn, ln = np.nonzero(on[new])  # cap vertex new[kn] (beyond its plane vj) on face ln
    kn = new[kn]
    rb = np.count_nonzero(on[kb], axis=1)
    kb2, jb2 = np.repeat(kb, rb), np.repeat(jb, rb)
    lb2 = np.nonzero(on[kb])[1]
    side = lb2 != jb2  # a base vertex on face l of C_j (l != j)
    J = np.concatenate([vj[kn], jb2[side]])
    L = np.concatenate([ln, lb2[side]])
    K = np.concatenate([kn, kb2[side]])
    uk, inv = np.unique(J * m + L, return_inverse=True)  # the faces (j, l): cap C_j's face on plane l
    fj, fl = np.divmod(uk, m)
    area = np.abs(_face_areas(p[K], inv, n[fl], len(uk))[0])
    height = np.maximum(d[fl] - np.einsum("ij,ij->i", n[fl], apex[fj]), 0.0)
    vol = np.bincount(fj, weights=area * height / 3.0, minlength=m)
    has = np.zeros(m, bool)
    has[vj[new]] = True
    out[has] = vol[has]
    return out


def polytope_volume(vertices: np.ndarray) -> float:
    """Volume of the convex hull of ``vertices`` (0 if flat), m^3."""
    try:
        return float(ConvexHull(np.asarray(vertices, np.float64)).volume)
    except (QhullError, ValueError):
        return 0.0


def inv_gamma(normals: np.ndarray) -> float:
    """1/gamma, gamma = min_{|u|=1} max_l n_l . u = 1 / (largest vertex norm of {x : n_l . x <= 1})."""
    n = np.asarray(normals, np.float64)
    try:
        verts = halfspaces_raw(np.c_[n, -np.ones(len(n))], np.zeros(3)).intersections
    except (QhullError, ValueError) as exc:  # the normals do not positively span R^3
        raise PolyccError(f"a polytope is unbounded (its normals do not surround the origin): {exc}") from None
    if not np.all(np.isfinite(verts)):
        raise PolyccError("a polytope is unbounded (its normals do not surround the origin); close it")
    return float(np.max(np.linalg.norm(verts, axis=1)))


def hull_halfplanes(points: np.ndarray, *, coplanar_tol: float = 1e-8) -> np.ndarray:
    """Half-planes [nx, ny, nz, d] (unit outward normals) of the convex hull of 3D points.

    Qhull triangulates facets; triangles on the same plane are merged into one half-plane.
    """
    hull = ConvexHull(np.asarray(points, dtype=np.float64))
    out: list[np.ndarray] = []
    for row in hull.equations:  # [n, -d], unit n, n . x + off <= 0 inside
        h = np.r_[row[:3], -row[3]]
        if not any(np.all(np.abs(h - o) <= coplanar_tol * (1 + np.abs(o))) for o in out):
            out.append(h)
    return np.array(out)


def axis_box(lo, hi) -> np.ndarray:
    """Half-planes of the axis-aligned box [lo, hi] (metres)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    rows = []
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        rows.append(np.r_[e, hi[i]])
        rows.append(np.r_[-e, -lo[i]])
    return np.array(rows)
