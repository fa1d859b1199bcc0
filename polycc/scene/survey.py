"""What a scene looks like before any heavy work: bounds, outlier groups, splat sizes, floor and up axis,
and the gravity-aligned, floor-at-z=0 transform of ``polycc align``. World frame of the scene as read
(after ``--transform``/``--scale``), its units (metres once the transform is right).

* Robust bounds: per-axis percentiles of the splat centres (``ROBUST_PCT``), next to the full bounds.
* Groups (:func:`splat_groups`): splat centres binned in cubic cells of side ``radius``; cells that
  touch (26-neighbourhood) form a group. Small groups far from the main body are the "far, isolated
  splats" of a capture (floaters, sky, stray points). Cells, not pairwise distances, so the cost is
  O(N log N) and bounded memory on millions of splats.
* Floor (:func:`detect_floor`): RANSAC on a sample of centres for the largest plane that most splats
  lie on one side of; up points from it toward the splats. Falls back to the direction of least
  spread (PCA) with an explicit "uncertain" flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

ROBUST_PCT = (0.5, 99.5)
METRIC_MAX_M = 20.0  # a robust extent above this is not a room in metres
METRIC_MIN_M = 0.2  # ... below this is not a flight volume in metres
FLOOR_MAX_BELOW = 0.02  # a plane with more of the splats below it is not the floor
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                        if (i, j, k) > (0, 0, 0)], np.int64)  # 13 forward offsets


def robust_bounds(points: np.ndarray, pct=ROBUST_PCT) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (lo, hi) percentiles of ``points`` (N, 3)."""
    return np.percentile(points, pct[0], axis=0), np.percentile(points, pct[1], axis=0)


def extent_warning(lo: np.ndarray, hi: np.ndarray) -> str | None:
    """A one-line warning when the robust extent does not look like metres, else None."""
    ext = float(np.max(hi - lo))
    if ext > METRIC_MAX_M:
        return (f"the scene's robust extent is {ext:.3g} units (over {METRIC_MAX_M:g} m): probably not metres; "
                "put it in metres with `polycc align SCENE --size L -o t.json` and --transform t.json")
    if ext < METRIC_MIN_M:
        return (f"the scene's robust extent is {ext:.3g} units (under {METRIC_MIN_M:g} m): probably not metres; "
                "put it in metres with `polycc align SCENE --size L -o t.json` and --transform t.json")
    return None


@dataclass
class Group:
    """A group of splats whose cells touch: ``count`` splats, centroid and bounds (scene units)."""

    count: int
    centroid: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    gap: float  # distance from the group's centroid to the nearest splat of the main body


@dataclass
class Groups:
    labels: np.ndarray  # (N,) group id per splat; 0 is the main body (the largest group)
    sizes: np.ndarray  # (G,) splats per group, group 0 largest
    radius: float


def splat_groups(centers: np.ndarray, radius: float) -> Groups:
    """Group splat centres whose cells of side ``radius`` touch; group 0 is the largest."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    c = np.asarray(centers, np.float64)
    cell = np.floor((c - c.min(axis=0)) / radius).astype(np.int64)
    span = cell.max(axis=0) + 3
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    ukey, inv = np.unique(key, return_inverse=True)
    ucell = np.stack([ukey // (span[1] * span[2]), (ukey // span[2]) % span[1], ukey % span[2]], axis=1)
    rows, cols = [], []
    for off in _NEIGHBOURS:
        nb = ucell + off
        nk = (nb[:, 0] * span[1] + nb[:, 1]) * span[2] + nb[:, 2]
        j = np.searchsorted(ukey, nk)
        j = np.minimum(j, len(ukey) - 1)
        hit = (ukey[j] == nk) & np.all(nb >= 0, axis=1)
        rows.append(np.flatnonzero(hit))
        cols.append(j[hit])
    r, q = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(r.size, np.int8), (r, q)), shape=(len(ukey), len(ukey)))
    _, comp = connected_components(g, directed=False)
    lab = comp[inv]
    sizes = np.bincount(lab)
    order = np.argsort(-sizes, kind="stable")
    remap = np.empty_like(order)
    remap[order] = np.arange(order.size)
    return Groups(labels=remap[lab], sizes=sizes[order], radius=float(radius))


def isolated_groups(centers: np.ndarray, groups: Groups, max_splats: int, top: int = 10) -> list[Group]:
    """The groups of fewer than ``max_splats`` splats, farthest from the main body first (at most ``top``)."""
    from scipy.spatial import cKDTree

    small = np.flatnonzero(groups.sizes < max_splats)
    if small.size == 0:
        return []
    main = centers[groups.labels == 0]
    tree = cKDTree(main[:: max(1, len(main) // 200_000)])
    out = []
    sel = np.isin(groups.labels, small)
    lab, pts = groups.labels[sel], centers[sel]
    order = np.argsort(lab, kind="stable")
    lab, pts = lab[order], pts[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    ends = np.r_[starts[1:], len(lab)]
    cents = np.array([pts[s:e].mean(axis=0) for s, e in zip(starts, ends)])
    gaps, _ = tree.query(cents)
    for i in np.argsort(-gaps)[:top]:
        s, e = starts[i], ends[i]
        out.append(Group(int(e - s), cents[i], pts[s:e].min(axis=0), pts[s:e].max(axis=0), float(gaps[i])))
    return out


def isolated_mask(centers: np.ndarray, radius: float, min_splats: int) -> tuple[np.ndarray, list[Group]]:
    """The splat-level floater filter: (N,) bool of the splats in groups of fewer than ``min_splats`` (never
    the main body), and those groups (farthest first)."""
    groups = splat_groups(centers, radius)
    small = groups.sizes < min_splats
    small[0] = False
    drop = small[groups.labels]
    return drop, (isolated_groups(centers, groups, min_splats, top=len(groups.sizes)) if drop.any() else [])


@dataclass
class Floor:
    """A detected floor: unit ``up`` normal (pointing to the splats), ``height`` = up . p on the plane,
    the fraction of sampled centres within ``tol`` of it, and whether the detection is uncertain."""

    up: np.ndarray
    height: float
    inliers: float
    one_sided: float
    tol: float
    method: str
    uncertain: bool = False
    notes: list = field(default_factory=list)


def _fit_plane(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    return n, float(n @ c)


def detect_floor(centers: np.ndarray, up_hint: np.ndarray | None = None, max_angle_deg: float = 20.0,
                 samples: int = 60_000, iters: int = 400, seed: int = 0) -> Floor:
    """RANSAC floor plane of ``centers`` (N, 3); with ``up_hint`` only planes within ``max_angle_deg`` of it."""
    rng = np.random.default_rng(seed)
    c = np.asarray(centers, np.float64)
    p = c if len(c) <= samples else c[rng.choice(len(c), samples, replace=False)]
    lo, hi = robust_bounds(p)
    tol = 0.01 * float(np.linalg.norm(hi - lo)) + 1e-12
    cos_max = np.cos(np.radians(max_angle_deg))
    tri = p[rng.integers(0, len(p), (iters, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1)
    ok = ln > 1e-12 * (tol * tol / 1e-4 + 1e-30)
    n, tri = n[ok] / ln[ok, None], tri[ok]
    if up_hint is not None:
        h = np.asarray(up_hint, np.float64) / np.linalg.norm(up_hint)
        flip = n @ h < 0
        n[flip] *= -1
        keep = n @ h >= cos_max
        n, tri = n[keep], tri[keep]
    best = None
    for k in range(0, len(n), 50):
        nn, d0 = n[k:k + 50], np.einsum("ij,ij->i", n[k:k + 50], tri[k:k + 50, 0])
        dist = p @ nn.T - d0  # (S, 50)
        inl = (np.abs(dist) <= tol).mean(axis=0)
        above = (dist > tol).mean(axis=0)
        below = (dist < -tol).mean(axis=0)
        side = np.maximum(above, below) / np.maximum(above + below, 1e-12)
        score = inl * (side >= 0.8)
        i = int(np.argmax(score))
        if score[i] > 0 and (best is None or score[i] > best[0]):
            best = (float(score[i]), nn[i], float(d0[i]), float(side[i]), bool(above[i] >= below[i]))
    if best is not None and best[0] >= 0.02:
        _, nn, d0, side, up_pos = best
        inl_pts = p[np.abs(p @ nn - d0) <= tol]
        n2, d2 = _fit_plane(inl_pts)  # least squares on the inliers
        if n2 @ nn < 0:
            n2, d2 = -n2, -d2
        if not up_pos:
            n2, d2 = -n2, -d2
        if up_hint is not None and n2 @ h < 0:
            n2, d2 = -n2, -d2
        frac = float((np.abs(p @ n2 - d2) <= tol).mean())
        return Floor(n2, d2, frac, side, tol, "RANSAC plane on splat centres")
    # no plane: least-spread direction (PCA), sign unknown
    ctr = p - p.mean(axis=0)
    _, _, vt = np.linalg.svd(ctr[:: max(1, len(ctr) // 20000)], full_matrices=False)
    u = vt[2] if up_hint is None else np.asarray(up_hint, np.float64) / np.linalg.norm(up_hint)
    if up_hint is None and np.sum(np.abs(u) * np.sign(u)) < 0:
        u = -u
    height = float(np.percentile(p @ u, ROBUST_PCT[0]))
    return Floor(u, height, 0.0, 0.0, tol, "no plane found: " + ("the given axis" if up_hint is not None else
                                                                  "least-spread direction (PCA)"),
                 uncertain=up_hint is None, notes=["no floor plane with >= 2 % of the splats"])


def rotation_to_z(u: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``u`` to +z (3x3)."""
    u = np.asarray(u, np.float64) / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    s, c = float(np.linalg.norm(v)), float(u @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * (K @ K)


@dataclass
class Alignment:
    """``matrix`` (4x4) maps the scene as read to the aligned frame: up = +z, floor at z = 0, the robust
    bounds centred on x = y = 0, and ``scale`` applied; ``floor`` is the plane it used."""

    matrix: np.ndarray
    floor: Floor
    scale: float
    scale_source: str
    extent: np.ndarray  # robust extent after alignment (aligned units)


def align(centers: np.ndarray, up: str = "auto", size: float | None = None,
          known: tuple[np.ndarray, np.ndarray, float] | None = None) -> Alignment:
    """Gravity-aligned, floor-at-z=0 similarity for ``centers`` (N, 3), scene frame.

    up: "auto" (RANSAC floor) or one of ``AXES`` ("+y" ...; the floor plane is then searched within 20 deg
    of it and its normal used if found). size: the robust longest side becomes ``size`` metres. known:
    (p1, p2, metres), two points of the scene frame and their true distance."""
    hint = None if up == "auto" else np.asarray(AXES[up], np.float64)
    fl = detect_floor(centers, hint)
    R = rotation_to_z(fl.up)
    q = centers @ R.T
    lo, hi = robust_bounds(q)
    # A plane with splats below it (a table top, the soil in a pot) is not the floor: then the floor is
    # the lowest of the splats (the robust low percentile along up).
    below = float(np.mean(q[:, 2] < fl.height - fl.tol))
    floor_z = fl.height
    if below > FLOOR_MAX_BELOW:
        floor_z = float(lo[2])
        fl.notes.append(f"{100 * below:.0f} % of the splats lie below the largest plane: floor = the lowest splats")
        fl.method += f"; {100 * below:.0f} % below it, so the floor is the lowest splats ({ROBUST_PCT[0]} %)"
        fl.height = floor_z
    t = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), floor_z])
    s, src = 1.0, "none (units kept)"
    if known is not None:
        p1, p2, dist = known
        d = float(np.linalg.norm(np.asarray(p1, np.float64) - np.asarray(p2, np.float64)))
        s, src = dist / d, f"known distance {dist:g} m between two points {d:.4g} units apart"
    elif size is not None:
        s, src = size / float(np.max(hi - lo)), f"robust longest side {float(np.max(hi - lo)):.4g} units = {size:g} m"
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = s * t
    return Alignment(M, fl, s, src, s * (hi - lo))
