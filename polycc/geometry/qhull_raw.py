"""scipy's qhull wrapper class, called without the Python bookkeeping of its public classes.

``scipy.spatial.ConvexHull`` and ``HalfspaceIntersection`` build every attribute they offer (points,
bounds, dual points, areas, vertex lists) around one qhull run. The merge stage ranks ~10^5 hulls and
the budget's reduction computes ~10^5 half-space intersections, and reads only a few of those, so
both call the class those two are built on (``scipy.spatial._qhull._Qhull``) the way they do, and read
only what they need: the results are the public classes' own, bit for bit. If that private class ever
changes, each function falls back to the public class.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

try:
    from scipy.spatial._qhull import _Qhull as _RawQhull
except ImportError:  # pragma: no cover
    _RawQhull = None


def hull_raw(pts: np.ndarray, options: bytes) -> tuple[float, np.ndarray, np.ndarray]:
    """(volume, simplices, equations) of ``ConvexHull(pts, qhull_options=options)``."""
    if _RawQhull is not None:
        try:
            q = _RawQhull(b"i", pts, options, required_options=b"Qt")
            try:
                simplices, _, equations, _, _ = q.get_simplex_facet_array()
                volume = q.volume_area()[0]
            finally:
                q.close()
            return float(volume), simplices, equations
        except QhullError:
            raise
        except Exception:  # pragma: no cover - private API drift
            pass
    h = ConvexHull(pts, qhull_options=options.decode())
    return float(h.volume), h.simplices, h.equations


class Halfspaces:
    """What the callers read of a ``HalfspaceIntersection``: ``intersections`` (V, 3), ``dual_facets``
    (the planes each vertex lies on) and ``dual_equations`` (V, 4)."""

    __slots__ = ("intersections", "dual_facets", "dual_equations")

    def __init__(self, intersections, dual_facets, dual_equations):
        self.intersections, self.dual_facets, self.dual_equations = intersections, dual_facets, dual_equations


def halfspaces_raw(halfspaces: np.ndarray, interior: np.ndarray) -> Halfspaces:
    """``HalfspaceIntersection(halfspaces, interior)`` (rows ``[A, b]``, ``A x + b <= 0``; 3-D, default
    options) reduced to :class:`Halfspaces`, its intersections computed by its own formula. Raises
    QhullError / ValueError as it does."""
    halfspaces = np.ascontiguousarray(halfspaces, dtype=np.double)
    interior = np.ascontiguousarray(interior, dtype=np.double)
    if _RawQhull is not None and halfspaces.ndim == 2 and halfspaces.shape[1] == 4 and interior.shape == (3,):
        try:
            q = _RawQhull(b"H", halfspaces, b"", required_options=None, incremental=False, interior_point=interior)
        except QhullError:
            raise
        except TypeError:  # pragma: no cover - private API drift
            q = None
        if q is not None:
            try:
                facets, equations = q.get_hull_facets()
            finally:
                q.close()
            return Halfspaces(equations[:, :-1] / -equations[:, -1:] + interior, facets, equations)
    hs = HalfspaceIntersection(halfspaces, interior)
    return Halfspaces(hs.intersections, hs.dual_facets, hs.dual_equations)
