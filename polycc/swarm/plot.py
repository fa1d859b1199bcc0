"""coverage.png: top view (x, y in m) of a swarm run -- obstacle columns of the free-cell grid, each
drone's last Voronoi cell (its free cells, projected), trajectories, starts, ends and the ToI peaks
with their sensing circles."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_coverage(path: str | Path, cmap, result, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 7.5), dpi=110)
    g = cmap.grid
    free = cmap.lut >= 0
    blocked = ~free.any(axis=2) | (free.sum(axis=2) < 0.5 * free.shape[2])  # mostly occupied columns
    ext = (g.lo[0], g.lo[0] + g.spacing * free.shape[0], g.lo[1], g.lo[1] + g.spacing * free.shape[1])
    ax.imshow(np.where(blocked.T, 0.55, 1.0), origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1,
              interpolation="nearest")
    colors = plt.cm.tab20(np.linspace(0, 1, max(result.n, 2)))
    for i in range(result.n):
        cell = result.cells[i] if i < len(result.cells) else []
        if len(cell):
            c = cmap.centres[cell]
            ax.scatter(c[:, 0], c[:, 1], s=6, color=colors[i], alpha=0.08, marker="s", linewidths=0)
        p = result.positions[i]
        ax.plot(p[:, 0], p[:, 1], "-", color=colors[i], lw=1.2)
        ax.plot(p[0, 0], p[0, 1], "o", color=colors[i], ms=6, mec="k")
        ax.plot(p[-1, 0], p[-1, 1], "X", color=colors[i], ms=8, mec="k")
        ax.annotate(str(i), p[-1, :2], textcoords="offset points", xytext=(4, 4), fontsize=8)
    t = result.targets
    for k in range(len(t.mu)):
        hit = np.isfinite(result.detected_at[k])
        ax.plot(t.mu[k, 0], t.mu[k, 1], "*", ms=16, color="gold" if hit else "red", mec="k")
        ax.add_patch(plt.Circle(t.mu[k, :2], t.sigma[k], fill=False, ls=":", color="k", lw=0.8))
        lab = f"{result.detected_at[k]:.1f} s" if hit else "missed"
        ax.annotate(lab, t.mu[k, :2], textcoords="offset points", xytext=(6, -12), fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
