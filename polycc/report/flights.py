"""trajectories.png (flights) and plan.png (a planned path) over the splats and the stored
polytopes (world frame, metres)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np


def plot_trajectories(path: str | Path, trials: list, polytope_vertices: list[np.ndarray], ellipsoids=None,
                      title: str = "", max_splats: int = 40000, seed: int = 0) -> Path:
    """Three views (top x-y, front x-z, side y-z) of the paths over the splats and polytopes.

    ``trials``: objects with ``positions`` (n, 3), ``start``, ``goal`` (m), ``success`` and
    ``collisions``, optionally ``waypoints`` (k, 3) m (a plan: drawn dashed); ``polytope_vertices``:
    the vertices of each stored polytope, metres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 6.5))
    draw_views(axes, trials, polytope_vertices, ellipsoids, max_splats, seed)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color="tab:green", lw=2, label="reached the goal"),
               Line2D([], [], color="tab:orange", lw=2, label="stuck / timeout"),
               Line2D([], [], color="tab:red", lw=2, label="collision"),
               Line2D([], [], marker="o", color="k", ls="", markersize=5, label="start"),
               Line2D([], [], marker="*", color="k", ls="", markersize=9, label="goal"),
               Line2D([], [], ls="--", marker=".", color="k", label="planned waypoints"),
               Patch(facecolor="tab:blue", alpha=0.25, edgecolor="tab:blue", label="stored polytopes"),
               Line2D([], [], marker=".", color="0.4", ls="", label="splat centres")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False, fontsize=11)
    fig.suptitle(title or "polycc SITL flights")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_plan(path: str | Path, waypoints: np.ndarray, polytope_vertices: list[np.ndarray], ellipsoids=None,
              profile: tuple[np.ndarray, np.ndarray] | None = None, margin: float = 0.0, title: str = "",
              max_splats: int = 40000, seed: int = 0) -> Path:
    """plan.png: the three views of a planned path (waypoints as dots) and, if ``profile`` =
    (arc length m, psi m) is given, psi along the path against the margin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w = np.asarray(waypoints, np.float64)
    drawn = SimpleNamespace(positions=w, waypoints=w, start=w[0], goal=w[-1], success=True, collisions=0)
    fig, axes = plt.subplots(1, 4 if profile is not None else 3, figsize=(24 if profile is not None else 18, 6.5))
    draw_views(axes[:3], [drawn], polytope_vertices, ellipsoids, max_splats, seed)
    if profile is not None:
        ax = axes[3]
        s, psi = profile
        ax.plot(s, psi, color="tab:green", linewidth=1.5, label="psi (reference kernel) along the plan")
        ax.axhline(margin, color="tab:orange", linestyle="--", linewidth=1, label=f"margin {margin:g} m")
        ax.axhline(0.0, color="tab:red", linewidth=1, label="psi = 0 (the filter's boundary)")
        ax.set_xlabel("arc length (m)")
        ax.set_ylabel("psi (m)")
        ax.set_title("clearance the drone's barrier sees")
        ax.legend(loc="best", fontsize=8)
    fig.suptitle(title or "polycc plan")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def draw_views(axes, trials: list, polytope_vertices: list[np.ndarray], ellipsoids=None, max_splats: int = 40000,
               seed: int = 0) -> None:
    """Top, front and side views on three matplotlib axes (see :func:`plot_trajectories`)."""
    from matplotlib.collections import PolyCollection
    from scipy.spatial import ConvexHull

    views = (("top (x-y)", 0, 1), ("front (x-z)", 0, 2), ("side (y-z)", 1, 2))
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
        shapes = []
        for v in verts:
            if top and float(v[:, 2].max()) < z0 + 0.15:
                continue
            q = v[:, [i, j]]
            try:
                shapes.append(q[ConvexHull(q).vertices])
            except Exception:
                continue
        if shapes:  # one collection: far faster to draw than a patch per polytope
            ax.add_collection(PolyCollection(shapes, closed=True, facecolors="tab:blue", alpha=0.12,
                                             edgecolors="tab:blue", linewidths=0.5))
        if pts is not None:
            keep = pts[:, 2] >= z0 + 0.15 if top else np.ones(len(pts), bool)
            cc = cols[keep] if isinstance(cols, np.ndarray) else cols
            ax.scatter(pts[keep, i], pts[keep, j], s=0.2, c=cc, alpha=0.5, linewidths=0, rasterized=True)
        for n, tr in enumerate(trials):
            c = "tab:green" if tr.success else ("tab:red" if tr.collisions > 0 else "tab:orange")
            ax.plot(tr.positions[:, i], tr.positions[:, j], color=c, linewidth=1.8)
            w = getattr(tr, "waypoints", None)
            if w is not None:
                ax.plot(w[:, i], w[:, j], "--.", color="k", linewidth=0.8, markersize=5, alpha=0.7)
            ax.plot(tr.start[i], tr.start[j], "o", color="k", markersize=4)
            ax.plot(tr.goal[i], tr.goal[j], "*", color="k", markersize=8)
        ax.set_title(name)
        ax.set_xlabel(f"{labels[i + 1]} (m)")
        ax.set_ylabel(f"{labels[j + 1]} (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
