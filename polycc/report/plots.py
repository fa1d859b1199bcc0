"""report.png: three views of the stored cover over the splat centres, and the n-vs-conservativeness curve.

Readable with hundreds of overlapping polytopes: each view fills every polytope with a colour for its
depth along the viewing axis (height in the top view) and draws the far ones first, like a depth map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

VIEWS = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))


def _outline(vertices: np.ndarray, a: int, b: int) -> np.ndarray | None:
    from scipy.spatial import ConvexHull, QhullError

    pts = vertices[:, [a, b]]
    try:
        h = ConvexHull(pts)
    except (QhullError, ValueError):
        return None
    return pts[h.vertices]


def write_report(
    path: str | Path,
    centers: np.ndarray,
    polytope_vertices: list[np.ndarray],
    curve: list[tuple[int, float, float]],
    chosen: tuple[int, float],
    title: str,
    max_points: int = 60_000,
    seed: int = 0,
) -> Path:
    """Write the report PNG.

    centers: (N, 3) splat centres (metres, world frame); polytope_vertices: vertices of each
    stored polytope; curve: (n, conservativeness, ci) points; chosen: (n, conservativeness).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    rng = np.random.default_rng(seed)
    pts = centers if len(centers) <= max_points else centers[rng.choice(len(centers), max_points, replace=False)]
    fig, axes = plt.subplots(2, 2, figsize=(16, 12), layout="constrained")
    axes = axes.ravel()
    allv = np.concatenate(polytope_vertices) if polytope_vertices else pts
    lo = np.minimum(pts.min(0), allv.min(0))
    hi = np.maximum(pts.max(0), allv.max(0))
    # Many polytopes overlap in projection: fill each with a colour for its depth along the viewing axis
    # and draw the far ones first, so a view reads like a depth map (the nearest surface on top).
    depth_axis = {(0, 1): (2, +1), (0, 2): (1, -1), (1, 2): (0, +1)}  # top: z up; front: looking +y; side: from +x
    cmap = plt.get_cmap("viridis")
    for ax, (name, a, b) in zip(axes[:3], VIEWS):
        ax.scatter(pts[:, a], pts[:, b], s=0.3, c="0.55", alpha=0.35, linewidths=0, rasterized=True)
        d, sgn = depth_axis[(a, b)]
        near = np.array([sgn * (v[:, d].max() if sgn > 0 else v[:, d].min()) for v in polytope_vertices]) \
            if polytope_vertices else np.zeros(0)
        dlo, dhi = float(lo[d]), float(hi[d])
        norm = plt.Normalize(dlo, max(dhi, dlo + 1e-9))
        outlines, colours = [], []
        for i in np.argsort(near):  # far first: a collection draws in its order (one artist, not one per polytope)
            o = _outline(polytope_vertices[i], a, b)
            if o is not None:
                val = polytope_vertices[i][:, d].max() if sgn > 0 else polytope_vertices[i][:, d].min()
                outlines.append(o)
                colours.append((*cmap(norm(val))[:3], 0.85))
        if outlines:
            ax.add_collection(PolyCollection(outlines, closed=True, facecolors=colours, edgecolors="0.15",
                                             linewidths=0.25))
        ax.set_xlim(lo[a] - 0.05, hi[a] + 0.05)
        ax.set_ylim(lo[b] - 0.05, hi[b] + 0.05)
        ax.set_aspect("equal")
        what = "xyz"[d] + (" (nearest on top)" if d != 2 else " (highest on top)")
        ax.set_title(f"{name}: {len(polytope_vertices)} polytopes, colour = {what}")
        ax.set_xlabel("xyz"[a] + " [m]")
        ax.set_ylabel("xyz"[b] + " [m]")
        sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
        fig.colorbar(sm, ax=ax, shrink=0.8, label="xyz"[d] + " [m]")
    ax = axes[3]
    if curve:
        c = np.array(sorted(curve))
        ax.errorbar(c[:, 0], c[:, 1], yerr=c[:, 2], fmt="o-", ms=3, label="H^n after budget (reduced, quantized)")
    ax.plot([chosen[0]], [chosen[1]], "r*", ms=14, label=f"chosen n = {chosen[0]}")
    ax.set_xscale("log")
    ax.set_xlabel("n (polytopes)")
    ax.set_ylabel("conservativeness Vol(union H) / Vol(V+)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title("trade-off")
    fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
