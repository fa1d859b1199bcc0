"""Convex polytopes in half-plane form, world frame, metres: ``P = {p : n_l . p <= d_l}``.

Rows are ``[nx, ny, nz, d]`` (float64 here). Each primitive exists once:

* :func:`is_bounded` -- P is bounded iff the normals positively span R^3, i.e. the origin is
  strictly inside their convex hull (qhull's half-space intersection does not detect an
  unbounded intersection reliably, so this is checked separately). ``min_gamma`` is the
  required depth of the origin in the hull of the unit normals (gamma = min_{|u|=1} max_l
  n_l . u); a positive margin also rules out needle-like polytopes.
* :func:`chebyshev_centre` -- centre and radius of the largest ball in P (HiGHS LP).
* :func:`polytope_vertices` -- vertices by half-space intersection (qhull), or None.
* :func:`inv_gamma` -- 1/gamma of a set of normals (the culling factor of the on-board layout).
* :func:`hull_halfplanes`, :func:`axis_box` -- half-planes of a convex hull of points / of a box.

``polycc.verify`` keeps its own independent copy of vertex enumeration on purpose.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from polycc.errors import PolyccError

MIN_PLANES = 4  # a bounded polytope in R^3 needs at least 4 half-planes


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
    from scipy.optimize import linprog

    h = np.asarray(h, np.float64)
    n, d = h[:, :3], h[:, 3]
    norms = np.linalg.norm(n, axis=1)
    res = linprog(c=[0, 0, 0, -1], A_ub=np.c_[n, norms], b_ub=d, bounds=[(None, None)] * 3 + [(0, None)],
                  method="highs")
    if res.status != 0 or res.x[3] <= 0:
        raise PolyccError("a polytope is empty, flat or unbounded; every polytope needs a non-empty interior")
    return res.x[:3], float(res.x[3])


def polytope_vertices(h: np.ndarray, interior: np.ndarray | None = None, min_gamma: float = 1e-9,
                      max_reach: float = 1e6) -> np.ndarray | None:
    """Vertices of ``{n . p <= d}`` (rows ``[n, d]``), or None if it is unbounded or degenerate.

    ``interior`` is a strictly interior point (default: the Chebyshev centre). Vertices farther
    than ``max_reach`` metres from it count as unbounded."""
    h = np.asarray(h, np.float64)
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
            v = HalfspaceIntersection(np.c_[h[:, :3], -h[:, 3]], interior).intersections
    except (QhullError, ValueError):
        return None
    if len(v) == 0 or not np.all(np.isfinite(v)) or np.abs(v - interior).max() > max_reach:
        return None
    return v


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
        verts = HalfspaceIntersection(np.c_[n, -np.ones(len(n))], np.zeros(3)).intersections
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
