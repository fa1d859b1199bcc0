"""trajectories.png: flights over the splats and the stored polytopes (world frame, metres)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_trajectories(path: str | Path, trials: list, polytope_vertices: list[np.ndarray], ellipsoids=None,
                      title: str = "", max_splats: int = 40000, seed: int = 0) -> Path:
    """Three views (top x-y, front x-z, side y-z) of the paths over the splats and polytopes.

    ``trials``: objects with ``positions`` (n, 3), ``start``, ``goal`` (m), ``success`` and
    ``collisions``; ``polytope_vertices``: the vertices of each stored polytope, metres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon
    from scipy.spatial import ConvexHull

    views = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.5))
    verts = [v for v in polytope_vertices if v is not None and len(v)]
    pts = cols = None
    if ellipsoids is not None and len(ellipsoids):
        rng = np.random.default_rng(seed)
        sel = rng.choice(len(ellipsoids), size=min(max_splats, len(ellipsoids)), replace=False)
        pts = ellipsoids.centers[sel]
        cols = ellipsoids.colors[sel] / 255.0 if ellipsoids.colors is not None else "0.4"
    labels = "axyz"
    # The top view leaves out the floor (polytopes and splats within 0.15 m of the lowest
    # polytope), which would hide everything else.
    z0 = min((float(v[:, 2].min()) for v in verts), default=0.0)
    for ax, (name, i, j) in zip(axes, views):
        top = j == 1
        for v in verts:
            if top and float(v[:, 2].max()) < z0 + 0.15:
                continue
            q = v[:, [i, j]]
            try:
                hull = ConvexHull(q)
                ax.add_patch(Polygon(q[hull.vertices], closed=True, facecolor="tab:blue", alpha=0.12,
                                     edgecolor="tab:blue", linewidth=0.5))
            except Exception:
                continue
        if pts is not None:
            keep = pts[:, 2] >= z0 + 0.15 if top else np.ones(len(pts), bool)
            cc = cols[keep] if isinstance(cols, np.ndarray) else cols
            ax.scatter(pts[keep, i], pts[keep, j], s=0.2, c=cc, alpha=0.5, linewidths=0, rasterized=True)
        for n, tr in enumerate(trials):
            c = "tab:green" if tr.success else ("tab:red" if tr.collisions > 0 else "tab:orange")
            ax.plot(tr.positions[:, i], tr.positions[:, j], color=c, linewidth=1.8)
            ax.plot(tr.start[i], tr.start[j], "o", color="k", markersize=4)
            ax.plot(tr.goal[i], tr.goal[j], "*", color="k", markersize=8)
        ax.set_title(name)
        ax.set_xlabel(f"{labels[i + 1]} (m)")
        ax.set_ylabel(f"{labels[j + 1]} (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color="tab:green", lw=2, label="reached the goal"),
               Line2D([], [], color="tab:orange", lw=2, label="stuck / timeout"),
               Line2D([], [], color="tab:red", lw=2, label="collision"),
               Line2D([], [], marker="o", color="k", ls="", markersize=5, label="start"),
               Line2D([], [], marker="*", color="k", ls="", markersize=9, label="goal"),
               Patch(facecolor="tab:blue", alpha=0.25, edgecolor="tab:blue", label="stored polytopes"),
               Line2D([], [], marker=".", color="0.4", ls="", label="splat centres")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False, fontsize=11)
    fig.suptitle(title or "polycc SITL flights")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
