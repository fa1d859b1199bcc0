"""Ground-truth clearance: exact distances from points to the splat ellipsoids (world frame, metres).

:class:`Clearance` answers the distance from each point of a path to the nearest ellipsoid,
exact (to float64 rounding: bisection on the Lagrange multiplier of the closest-point problem)
wherever it can matter. Only nearby ellipsoids are evaluated: a KD-tree over the centres gives
upper and lower bounds per point, and exact distances are computed only where the lower bound
can matter. :func:`densify` resamples a path so the reported minimum is within half the spacing
of the continuous minimum along the piecewise-linear path.
"""

from __future__ import annotations

import math

import numpy as np

SAMPLE_SPACING_M = 0.0025


def point_ellipsoid_distance(y: np.ndarray, a: np.ndarray, iters: int = 100) -> np.ndarray:
    """Exact distance from points ``y`` (n, 3) in each ellipsoid's principal frame to the
    ellipsoids {sum (y_i/a_i)^2 <= 1} with semi-axes ``a`` (n, 3); 0 inside.

    Outside, the closest point is x_i = a_i^2 y_i / (t + a_i^2) with t > 0 the root of
    f(t) = sum (a_i y_i / (t + a_i^2))^2 - 1, decreasing on (0, |a|_max |y|]; bisection to
    float64 resolution."""
    y = np.abs(np.asarray(y, np.float64))
    a = np.asarray(a, np.float64)
    inside = np.sum((y / a) ** 2, axis=1) <= 1.0
    a2 = a * a
    lo = np.zeros(len(y))
    hi = np.max(a, axis=1) * np.linalg.norm(y, axis=1) + 1e-300
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        f = np.sum((a * y / (mid[:, None] + a2)) ** 2, axis=1) - 1.0
        pos = f > 0
        lo = np.where(pos, mid, lo)
        hi = np.where(pos, hi, mid)
        if np.all(hi - lo <= 1e-15 * np.maximum(hi, 1e-300)):
            break
    t = 0.5 * (lo + hi)
    x = a2 * y / (t[:, None] + a2)
    d = np.linalg.norm(y - x, axis=1)
    return np.where(inside, 0.0, d)


class Clearance:
    """Distances from points to the nearest splat ellipsoid (ground truth), exact where it matters."""

    def __init__(self, ellipsoids, k_nn: int = 16):
        from scipy.spatial import cKDTree

        e = ellipsoids
        self.centers = np.asarray(e.centers, np.float64)
        self.R = np.asarray(e.rotations, np.float64)
        self.a = np.asarray(e.sigmas, np.float64) * float(e.k)
        amax = self.a.max(axis=1)
        self.amin = self.a.min(axis=1)
        self.amax = amax
        big_cut = max(0.1, 20.0 * float(np.median(amax))) if len(amax) else 0.1
        self.big = np.flatnonzero(amax > big_cut)
        self.small = np.flatnonzero(amax <= big_cut)
        self.amax_small = float(amax[self.small].max()) if len(self.small) else 0.0
        self.tree = cKDTree(self.centers[self.small]) if len(self.small) else None
        self.k = min(k_nn, len(self.small))

    def _exact(self, p: np.ndarray, idx: np.ndarray) -> float:
        if len(idx) == 0:
            return math.inf
        y = np.einsum("nji,nj->ni", self.R[idx], p[None, :] - self.centers[idx])
        return float(point_ellipsoid_distance(y, self.a[idx]).min())

    def bounds(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point (lower, upper) bounds on the distance to the nearest ellipsoid."""
        n = len(P)
        lb = np.full(n, np.inf)
        ub = np.full(n, np.inf)
        if self.tree is not None and self.k > 0:
            d, j = self.tree.query(P, k=self.k)
            d, j = d.reshape(n, -1), j.reshape(n, -1)
            g = self.small[j]
            ub = np.minimum(ub, np.min(d - self.amin[g], axis=1))
            lb = np.minimum(np.min(d - self.amax[g], axis=1), d[:, -1] - self.amax_small)
        if len(self.big):
            db = np.linalg.norm(P[:, None, :] - self.centers[self.big][None], axis=2)
            ub = np.minimum(ub, np.min(db - self.amin[self.big], axis=1))
            lb = np.minimum(lb, np.min(db - self.amax[self.big], axis=1))
        return np.maximum(lb, 0.0), np.maximum(ub, 0.0)

    def exact_at(self, p: np.ndarray, ub: float) -> float:
        """Exact distance from one point, given an upper bound ``ub`` on it."""
        cand = []
        if self.tree is not None:
            j = np.asarray(self.tree.query_ball_point(p, ub + self.amax_small), dtype=np.int64)
            if len(j):
                g = self.small[j]
                dd = np.linalg.norm(self.centers[g] - p, axis=1)
                cand.append(g[dd - self.amax[g] <= ub])
        if len(self.big):
            dd = np.linalg.norm(self.centers[self.big] - p, axis=1)
            cand.append(self.big[dd - self.amax[self.big] <= ub])
        idx = np.concatenate(cand) if cand else np.zeros(0, np.int64)
        return self._exact(p, idx)

    def evaluate(self, P: np.ndarray, radius: float) -> tuple[float, int, np.ndarray]:
        """(minimum clearance = distance - radius, collision events, exact-or-lower-bound distances).

        A collision event is a maximal run of consecutive points whose exact distance is
        below ``radius`` (the agent ball touches a splat)."""
        P = np.asarray(P, np.float64).reshape(-1, 3)
        lb, ub = self.bounds(P)
        thr = max(float(ub.min()), radius)
        dist = lb.copy()
        for i in np.flatnonzero(lb <= thr):
            dist[i] = self.exact_at(P[i], float(ub[i]))
        hit = dist < radius
        events = int(np.count_nonzero(hit[1:] & ~hit[:-1]) + (1 if hit[0] else 0)) if len(hit) else 0
        return float(dist.min()) - radius, events, dist


def densify(P: np.ndarray, spacing: float = SAMPLE_SPACING_M) -> np.ndarray:
    """Piecewise-linear resampling so consecutive points are at most ``spacing`` apart."""
    P = np.asarray(P, np.float64)
    if len(P) < 2:
        return P
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    k = np.maximum(1, np.ceil(seg / spacing).astype(np.int64))
    i = np.repeat(np.arange(len(seg)), k)
    t = (np.arange(len(i)) - np.repeat(np.cumsum(k) - k, k) + 1) / np.repeat(k, k)
    return np.concatenate([P[:1], P[i] + t[:, None] * (P[i + 1] - P[i])])
