"""What the voxel floater filter (``--min-splats-per-voxel M > 1``) gives up, computed exactly.

The filter removes occupied voxels touched by fewer than M distinct ellipsoids. The cover is
then certified only against the FILTERED occupancy: a splat that touches a removed voxel may
lie partly outside every kept voxel, and so outside the cover. :func:`floater_loss` reports

* ``voxels_removed``: voxels the filter removed;
* ``splats_not_fully_covered``: kept splats whose ellipsoid meets a removed voxel (the exact
  ellipsoid-box test of :mod:`polycc.geometry.ellipsoid_box`, float error toward "meets", so this count
  never misses one);
* ``max_depth_outside_m``: a certified upper bound on ``max_{p in E_i} dist(p, K)`` over those
  splats, K the union of the kept voxels (metres, world frame), and ``depth_lower_m``, a
  lower bound attained at a point of an ellipsoid; their gap is at most ``tol_m``.

The depth is a branch and bound over boxes inside the removed voxels that meet an ellipsoid:
``dist(., K)`` is 1-Lipschitz, so over a box of centre c and half-diagonal h it is at most
``dist(c, K) + h`` (upper bound), and a box centre inside the ellipsoid is a witness (lower
bound). Boxes are split in 8 until the bounds meet within ``tol_m``. Distances to K are exact
point-to-box distances to the nearest kept voxels (a KD-tree over their centres).
"""

from __future__ import annotations

import numpy as np

from polycc.geometry.ellipsoid_box import boxes_intersect
from polycc.scene.ellipsoids import Ellipsoids

DEPTH_TOL_M = 1e-3
MAX_BOXES = 400_000  # work cap per refinement round; the bound stays valid (only looser) if reached
MAX_ROUNDS = 24
_CHILD = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.float64)


class _DistanceToVoxels:
    """Exact Euclidean distance from points to a union of axis-aligned voxels (metres)."""

    def __init__(self, lower_corners: np.ndarray, g: float):
        from scipy.spatial import cKDTree

        self.g = float(g)
        self.centres = np.asarray(lower_corners, np.float64) + 0.5 * self.g
        self.tree = cKDTree(self.centres)
        self.k = min(64, len(self.centres))
        self.h = 0.5 * np.sqrt(3.0) * self.g  # centre-to-corner

    def _box_dist(self, p: np.ndarray, c: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.maximum(np.abs(p - c) - 0.5 * self.g, 0.0), axis=-1)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0)
        d, j = self.tree.query(p, k=self.k)
        d, j = d.reshape(len(p), -1), j.reshape(len(p), -1)
        bd = self._box_dist(p[:, None, :], self.centres[j])
        best = bd.min(axis=1)
        # a voxel farther than best + h (centre distance) cannot be closer as a box
        unsure = np.flatnonzero(d[:, -1] < best + self.h) if self.k < len(self.centres) else np.zeros(0, int)
        for i in unsure:
            near = np.asarray(self.tree.query_ball_point(p[i], best[i] + self.h), np.int64)
            if len(near):
                best[i] = min(best[i], float(self._box_dist(p[i], self.centres[near]).min()))
        return best


def _pairs(ell: Ellipsoids, removed_lo: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """(splat, removed voxel) pairs whose ellipsoid meets the voxel (closed boxes)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(removed_lo + 0.5 * g)
    half = ell.aabb_halfwidth()
    reach = half.max(axis=1) + 0.5 * g + 1e-9
    si, vi = [], []
    for i, near in enumerate(tree.query_ball_point(ell.centers, reach, p=np.inf)):
        if near:
            si.append(np.full(len(near), i, np.int64))
            vi.append(np.asarray(near, np.int64))
    if not si:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    si, vi = np.concatenate(si), np.concatenate(vi)
    lo = removed_lo[vi]
    sub = ell.subset(si)
    hit = boxes_intersect(sub.centers, sub.whitening(), lo, lo + g)
    return si[hit], vi[hit]


def _inside(ell: Ellipsoids, si: np.ndarray, p: np.ndarray) -> np.ndarray:
    M = ell.whitening()[si]
    w = np.einsum("nij,nj->ni", M, p - ell.centers[si])
    return np.einsum("ni,ni->n", w, w) <= 1.0


def floater_loss(ell: Ellipsoids, kept: np.ndarray, removed: np.ndarray, g: float, origin: np.ndarray,
                 tol_m: float = DEPTH_TOL_M) -> dict:
    """Splats the floater filter leaves partly uncovered and how deep (see module docstring).

    ``kept``/``removed``: (N, 3) int voxel indices after/removed by the filter; ``g`` metres,
    ``origin`` (3,) metres.  ``out["splats"]`` holds the indices of the splats not fully covered
    (drop it before writing JSON: :func:`loss_record`)."""
    origin = np.asarray(origin, np.float64)
    out = {"voxels_removed": int(len(removed)), "splats_not_fully_covered": 0, "max_depth_outside_m": 0.0,
           "depth_lower_m": 0.0, "depth_tolerance_m": float(tol_m), "worst_splat": None,
           "splats": np.zeros(0, np.int64)}
    if len(removed) == 0 or len(ell) == 0:
        return out
    rlo = origin + np.asarray(removed, np.float64) * g
    si, vi = _pairs(ell, rlo, g)
    out["splats_not_fully_covered"] = int(np.unique(si).size)
    out["splats"] = np.unique(si)
    if len(si) == 0:
        return out
    if len(kept) == 0:  # nothing kept at all: the whole scene is outside
        lo, hi = ell.bounds()
        out["max_depth_outside_m"] = float(np.linalg.norm(hi - lo))
        return out
    dist = _DistanceToVoxels(origin + np.asarray(kept, np.float64) * g, g)
    lo = rlo[vi]
    size = np.full(len(si), float(g))
    lower, worst, closed_max, capped = 0.0, None, 0.0, False
    for _ in range(MAX_ROUNDS):
        c = lo + 0.5 * size[:, None]
        dc = dist(c)
        ub = dc + 0.5 * np.sqrt(3.0) * size
        wit = _inside(ell, si, c)
        if wit.any():
            k = int(np.argmax(np.where(wit, dc, -1.0)))
            if dc[k] > lower:
                lower, worst = float(dc[k]), int(si[k])
        open_ = ub > lower + tol_m
        if (~open_).any():
            closed_max = max(closed_max, float(ub[~open_].max()))
        if not open_.any():
            break
        if int(open_.sum()) * 8 > MAX_BOXES:  # the bound stays valid, only looser
            closed_max, capped = max(closed_max, float(ub[open_].max())), True
            break
        si, lo, size = si[open_], lo[open_], size[open_] * 0.5
        lo = (lo[:, None, :] + _CHILD[None] * size[:, None, None]).reshape(-1, 3)
        si, size = np.repeat(si, 8), np.repeat(size, 8)
        sub = ell.subset(si)
        meet = boxes_intersect(sub.centers, sub.whitening(), lo, lo + size[:, None])
        si, lo, size = si[meet], lo[meet], size[meet]
        if len(si) == 0:
            break
    else:
        closed_max, capped = max(closed_max, float(ub.max())), True
    out.update(max_depth_outside_m=max(closed_max, lower), depth_lower_m=lower, worst_splat=worst,
               depth_capped=capped)
    return out


def floater_text(stats: dict) -> str | None:
    """One line on what the floater filter gave up (None without the filter)."""
    f = stats.get("floater_filter")
    m = stats.get("min_splats_per_voxel", 1)
    if m <= 1:
        return None
    if not f or not f["voxels_removed"]:
        return f"floater filter M = {m}: no voxel removed, the cover holds every splat"
    return (f"floater filter M = {m}: {f['voxels_removed']:,} voxels removed; {f['splats_not_fully_covered']:,} splats "
            f"then NOT fully covered, up to {f['max_depth_outside_m']:.4f} m outside the cover (certified against "
            "the filtered occupancy only)")


def loss_record(loss: dict) -> dict:
    """The JSON part of a :func:`floater_loss` result (everything but the index array)."""
    return {k: v for k, v in loss.items() if k != "splats"}


__all__ = ["floater_loss", "loss_record", "DEPTH_TOL_M"]
