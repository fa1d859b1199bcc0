"""report.png: three views of the stored cover over the splat centres, and the n-vs-conservativeness curve."""

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
    from matplotlib.patches import Polygon

    rng = np.random.default_rng(seed)
    pts = centers if len(centers) <= max_points else centers[rng.choice(len(centers), max_points, replace=False)]
    fig, axes = plt.subplots(1, 4, figsize=(22, 5.5), gridspec_kw={"width_ratios": [1, 1, 1, 1.1]})
    allv = np.concatenate(polytope_vertices) if polytope_vertices else pts
    lo = np.minimum(pts.min(0), allv.min(0))
    hi = np.maximum(pts.max(0), allv.max(0))
    colors = plt.cm.tab20(np.arange(len(polytope_vertices)) % 20)
    for ax, (name, a, b) in zip(axes[:3], VIEWS):
        ax.scatter(pts[:, a], pts[:, b], s=0.2, c="0.35", alpha=0.4, linewidths=0)
        for v, col in zip(polytope_vertices, colors):
            o = _outline(v, a, b)
            if o is not None:
                ax.add_patch(Polygon(o, closed=True, facecolor=(*col[:3], 0.18), edgecolor=col, linewidth=0.7))
        ax.set_xlim(lo[a] - 0.05, hi[a] + 0.05)
        ax.set_ylim(lo[b] - 0.05, hi[b] + 0.05)
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xlabel("xyz"[a] + " [m]")
        ax.set_ylabel("xyz"[b] + " [m]")
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
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
