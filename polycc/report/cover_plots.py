"""Pictures of a cover: the n-vs-conservativeness trade-off and a 3-view render of H^n."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_tradeoff(curves: dict, path: str | Path, title: str = "") -> Path:
    """``curves``: name -> list of (n, conservativeness, ci95). Log-x plot like the paper's Fig. 4b."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for name, pts in curves.items():
        pts = sorted(pts)
        n = np.array([p[0] for p in pts])
        c = np.array([p[1] for p in pts])
        e = np.array([p[2] for p in pts])
        ax.errorbar(n, c, yerr=e, marker="o", ms=3, capsize=2, label=f"merge cost: {name}")
    ax.set_xscale("log")
    ax.set_yscale("log")  # the interesting range is just above 1
    for n in (10, 30, 50, 100, 150):
        ax.axvline(n, color="0.8", lw=0.6, zorder=0)
    ax.set_xlabel("number of polytopes n (grey: the paper's flight counts)")
    ax.set_ylabel("conservativeness Vol(U H^n) / Vol(V+)")
    ax.axhline(1.0, color="0.5", lw=0.8, ls=":")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title(title or "PolyMerge trade-off")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def _hull2d(p: np.ndarray) -> np.ndarray:
    """Convex hull (counter-clockwise) of 2-D points, monotone chain."""
    p = np.unique(np.round(p, 12), axis=0)
    if len(p) < 3:
        return p

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def half(pts):
        out = []
        for q in pts:
            while len(out) >= 2 and cross(out[-2], out[-1], q) <= 0:
                out.pop()
            out.append(q)
        return out

    lower, upper = half(p), half(p[::-1])
    return np.array(lower[:-1] + upper[:-1])


def plot_cover_views(polytopes: list, centers: np.ndarray, path: str | Path, title: str = "", max_points: int = 60_000,
                     seed: int = 0) -> Path:
    """Top (x-y), front (x-z) and side (y-z) views of the polytopes over the splat centres."""
    from matplotlib.collections import PolyCollection

    plt = _plt()
    rng = np.random.default_rng(seed)
    pts = centers if len(centers) <= max_points else centers[rng.choice(len(centers), max_points, replace=False)]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), dpi=110)
    cmap = plt.get_cmap("tab20")
    for ax, (a, b, name) in zip(axes, [(0, 1, "top (x-y)"), (0, 2, "front (x-z)"), (1, 2, "side (y-z)")]):
        polys = [_hull2d(P.vertices[:, [a, b]]) for P in polytopes]
        colors = [cmap(i % 20) for i in range(len(polys))]
        ax.add_collection(PolyCollection(polys, facecolors=[(*c[:3], 0.25) for c in colors],
                                         edgecolors=[(*c[:3], 0.9) for c in colors], linewidths=0.6))
        if len(pts):
            ax.scatter(pts[:, a], pts[:, b], s=0.2, c="k", alpha=0.35, linewidths=0)
        allv = np.concatenate([P.vertices for P in polytopes] + ([pts] if len(pts) else []))
        lo, hi = allv.min(axis=0), allv.max(axis=0)
        pad = 0.03 * max(float((hi - lo).max()), 1e-3)
        ax.set_xlim(lo[a] - pad, hi[a] + pad)
        ax.set_ylim(lo[b] - pad, hi[b] + pad)
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("xyz"[b] + " (m)")
        ax.set_title(name)
    fig.suptitle(title or f"{len(polytopes)} polytopes")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
