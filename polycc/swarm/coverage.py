"""Decentralized coverage (seed 003): a Gaussian-mixture density of targets of interest (ToI), the
deadlock-aware guided map (Eq. 8) from the certified free-cell grid of :mod:`polycc.plan`, and three
per-drone nominal controllers that write the app's goal.  Metres, world frame.

* ``guided`` (ours): density ``Σ_k w_k exp(-NF_k(q)² / 2σ_k²)`` with ``NF_k`` the cost-to-go from peak k
  on the 26-connected free grid (Dijkstra, exact on the grid); the drone's cell is its Voronoi cell
  among the broadcast positions, restricted to the free cells it can reach inside the cell; goal: the
  cell's density centroid, snapped to a reachable cell and approached along the grid path (lookahead).
* ``lloyd``: Eq. 3 as written, Euclidean density, the centroid of the whole Voronoi cell flown straight.
* ``repulsive``: attraction to the nearest undetected peak plus inverse-square repulsion from neighbours.

Every controller uses only its drone's broadcast position, its neighbours' broadcast positions, the
stored cover (through the grid) and the detected-peak set; the safety filter on board is unchanged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError

CONTROLLERS = ("guided", "lloyd", "repulsive")
LOOKAHEAD_M = 1.0  # m: at the default CLF gain (2/s) the app flies at vmax 0.5 m/s up to 0.5 m before it


@dataclass
class Targets:
    """The ToI Gaussian mixture: centres (K, 3) m, sigma (K,) m, weights (K,)."""

    mu: np.ndarray
    sigma: np.ndarray
    weight: np.ndarray

    def to_json(self) -> dict:
        return {"targets": [{"x": float(m[0]), "y": float(m[1]), "z": float(m[2]), "sigma": float(s),
                             "weight": float(w)} for m, s, w in zip(self.mu, self.sigma, self.weight)]}


def load_targets(path: str | Path) -> Targets:
    """``{"targets": [{"x","y","z","sigma"(m, default 0.4),"weight"(default 1)}, ...]}`` or a list of [x, y, z]."""
    try:
        d = json.loads(Path(path).read_text())
        items = d["targets"] if isinstance(d, dict) else d
        mu, sig, w = [], [], []
        for t in items:
            if isinstance(t, dict):
                mu.append([float(t["x"]), float(t["y"]), float(t["z"])])
                sig.append(float(t.get("sigma", 0.4)))
                w.append(float(t.get("weight", 1.0)))
            else:
                mu.append([float(v) for v in t][:3])
                sig.append(0.4)
                w.append(1.0)
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise PolyccError(f"{path}: not a targets file ({exc}); write {{\"targets\": [{{\"x\": 1, \"y\": 2, \"z\": 1, "
                          "\"sigma\": 0.4}}]}}") from None
    if not mu or any(s <= 0 for s in sig) or any(v <= 0 for v in w):
        raise PolyccError(f"{path}: needs at least one target, each with sigma > 0 m and weight > 0")
    return Targets(np.asarray(mu, float), np.asarray(sig, float), np.asarray(w, float))


class CoverageMap:
    """The free cells of a :class:`polycc.plan.planner.NavMap` grid as a graph, and the per-peak
    cost-to-go fields NF_k (m; inf where unreachable)."""

    def __init__(self, nav, targets: Targets):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        free = nav._free.astype(bool)
        idx = np.argwhere(free)
        if len(idx) < 2:
            raise PolyccError("the coverage grid has fewer than 2 free cells; use a finer --grid or a smaller "
                              "--radius")
        self.spacing = float(nav.spacing)
        self.grid = nav.grid
        self.centres = nav.grid.centres(idx)
        self.ijk = idx  # (M, 3) grid cell of each free cell
        shape = np.asarray(free.shape)
        lut = -np.ones(free.shape, np.int64)
        lut[tuple(idx.T)] = np.arange(len(idx))
        self.lut = lut
        rows, cols, lens = [], [], []
        for d in np.argwhere(np.ones((3, 3, 3))) - 1:
            if not d.any() or tuple(d) < (0, 0, 0):
                continue
            nb = idx + d
            ok = np.all((nb >= 0) & (nb < shape), axis=1)
            j = np.full(len(idx), -1)
            j[ok] = lut[tuple(nb[ok].T)]
            m = j >= 0
            rows.append(np.flatnonzero(m))
            cols.append(j[m])
            lens.append(np.full(m.sum(), self.spacing * float(np.linalg.norm(d))))
        r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(lens)
        n = len(idx)
        self.graph = coo_matrix((np.r_[w, w], (np.r_[r, c], np.r_[c, r])), shape=(n, n)).tocsr()
        self.targets = targets
        src = self.nearest(targets.mu)
        self.nf = np.atleast_2d(dijkstra(self.graph, indices=src))  # (K, M)
        self.eu = np.linalg.norm(self.centres[None] - targets.mu[:, None], axis=2)

    def nearest(self, p) -> np.ndarray:
        """Index of the free cell nearest to each point (Euclidean, cell centres)."""
        from scipy.spatial import cKDTree

        if not hasattr(self, "_tree"):
            self._tree = cKDTree(self.centres)
        return self._tree.query(np.asarray(p, float).reshape(-1, 3))[1]

    def density(self, kind: str, alive: np.ndarray) -> np.ndarray:
        """log of the density at every free cell (-inf: none), over the undetected peaks ``alive``:
        kept in logs because a cell metres from every peak has exp(-d²/2σ²) below 1e-12, and the
        centroid only needs the weights relative to the cell's largest."""
        t = self.targets
        dist = self.nf if kind == "guided" else self.eu
        if not alive.any():
            return np.full(dist.shape[1], -np.inf)
        lg = np.log(t.weight[alive])[:, None] - np.square(dist[alive]) / (2.0 * t.sigma[alive, None] ** 2)
        return np.logaddexp.reduce(lg, axis=0)


def voronoi_cells(cm: CoverageMap, gens: np.ndarray) -> np.ndarray:
    """For every free cell, the index of the nearest generator (broadcast position)."""
    g = np.asarray(gens, float).reshape(-1, 3)
    d2 = (g * g).sum(1)[None, :] - 2.0 * (cm.centres @ g.T)  # |c|^2 is common to every generator
    return np.argmin(d2, axis=1)


def _relative(logd: np.ndarray) -> np.ndarray | None:
    """Weights exp(log d - max) (None when the cell holds no density)."""
    m = float(np.max(logd)) if len(logd) else -np.inf
    if not np.isfinite(m):
        return None
    return np.exp(logd - m)


class Controller:
    """One drone's nominal (runs in its own ground process on hardware; here one object per drone)."""

    def __init__(self, cmap: CoverageMap, kind: str):
        if kind not in CONTROLLERS:
            raise PolyccError(f"controller {kind!r}: choose one of {', '.join(CONTROLLERS)}")
        self.cmap, self.kind = cmap, kind
        self.cell = np.zeros(0, np.int64)  # the free cells of the last Voronoi cell (for the plot)

    def goal(self, own: np.ndarray, others: np.ndarray, alive: np.ndarray, dens: np.ndarray,
             cell: np.ndarray | None = None) -> np.ndarray:
        """The next goal (3,) m from the own and the neighbours' broadcast positions; ``cell`` (free-cell
        indices of the drone's Voronoi cell among those positions) may be given when the caller has
        partitioned the cells for every drone at once (:func:`voronoi_cells`, the same result)."""
        cm = self.cmap
        own = np.asarray(own, float)
        if self.kind == "repulsive":
            return self._repulsive(own, others, alive)
        if cell is None:
            gens = np.vstack([own[None], np.asarray(others, float).reshape(-1, 3)])
            cell = np.flatnonzero(voronoi_cells(cm, gens) == 0)
        self.cell = cell
        if len(cell) == 0:
            return own
        if self.kind == "lloyd":
            w = _relative(dens[cell])
            if w is None:
                return own
            c = (w[:, None] * cm.centres[cell]).sum(0) / w.sum()
            return cm.centres[cell[np.argmin(((cm.centres[cell] - c) ** 2).sum(1))]]
        return self._guided(own, cell, dens)

    def _guided(self, own, cell, dens) -> np.ndarray:
        from scipy import ndimage

        from polycc.plan.native import astar

        cm = self.cmap
        start = int(cm.nearest(own)[0])
        if not np.any(cell == start):
            cell = np.r_[cell, start]
        lo = cm.ijk[cell].min(0)
        loc = cm.ijk[cell] - lo  # the cell's bounding box of the grid, local indices
        mask = np.zeros(tuple(loc.max(0) + 1), np.uint8)
        mask[tuple(loc.T)] = 1
        labels, _ = ndimage.label(mask, structure=np.ones((3, 3, 3)))  # 26-connected, as the grid moves
        s_loc = cm.ijk[start] - lo
        reach = labels[tuple(loc.T)] == labels[tuple(s_loc)]
        w = _relative(np.where(reach, dens[cell], -np.inf))
        if w is None:
            return own
        c = (w[:, None] * cm.centres[cell]).sum(0) / w.sum()
        r_idx = np.flatnonzero(reach)
        tgt = int(cell[r_idx[np.argmin(((cm.centres[cell[r_idx]] - c) ** 2).sum(1))]])
        if tgt == start:
            return cm.centres[start]
        ends = np.ravel_multi_index((cm.ijk[[start, tgt]] - lo).T, mask.shape)
        cost, path, _ = astar(mask, cm.spacing, ends[:1], np.zeros(1), ends[1:], np.zeros(1), cm.ijk[tgt] - lo, 0.0)
        if not np.isfinite(cost) or len(path) < 2:
            return own
        pts = cm.grid.centres(np.stack(np.unravel_index(path, mask.shape), axis=-1) + lo)
        along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
        return pts[int(np.searchsorted(along, LOOKAHEAD_M, side="right")) - 1]

    def _repulsive(self, own, others, alive) -> np.ndarray:
        t = self.cmap.targets
        live = np.flatnonzero(alive)
        if len(live) == 0:
            return own
        k = live[np.argmin(np.linalg.norm(t.mu[live] - own, axis=1))]
        a = t.mu[k] - own
        g = a / max(np.linalg.norm(a), 1e-9)
        for q in np.asarray(others, float).reshape(-1, 3):
            d = own - q
            r = float(np.linalg.norm(d))
            if 1e-6 < r < 1.5:
                g = g + 0.3 * d / r ** 3
        n = float(np.linalg.norm(g))
        return own if n < 1e-9 else own + min(LOOKAHEAD_M, float(np.linalg.norm(a))) * g / n
