"""Monte Carlo volume of a union of convex polytopes, with a confidence interval.

Estimator: for each polytope k, draw points uniformly in its bounding box B_k and score
``1[x in P_k] / m(x)`` with m(x) the number of polytopes containing x. Summed over k,
``sum_k Vol(B_k) * mean(score_k)`` is an unbiased estimate of Vol(union) (each point of
the union is counted once in total), and the per-polytope sample variances give the
standard error. Used for conservativeness = Vol(union) / Vol(V+).

The wasted volume Vol(union \\ V+) is small next to Vol(union) for a good cover, so the
difference of two volume estimates would drown it in noise; :func:`union_waste` scores
only the sampled points outside V+ instead, which gives the waste with a relative error
of about 1/sqrt(number of points outside V+).
"""

from __future__ import annotations

from typing import Callable

import numpy as np


def inside(h: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points p (M, 3) in {x : n . x <= d} for rows h (H, 4)."""
    return np.all(p @ h[:, :3].T <= h[:, 3], axis=1)


def in_voxels(indices: np.ndarray, origin, g: float) -> Callable[[np.ndarray], np.ndarray]:
    """Membership test for the voxel set V+ (voxel i = [origin + i g, origin + (i+1) g], metres):
    points (M, 3) -> (M,) bool."""
    idx = np.asarray(indices, np.int64)
    lo = idx.min(axis=0)
    dims = idx.max(axis=0) - lo + 1
    keys = np.sort(np.ravel_multi_index((idx - lo).T, dims))
    origin = np.asarray(origin, np.float64)

    def test(points: np.ndarray) -> np.ndarray:
        i = np.floor((points - origin) / g).astype(np.int64) - lo
        ok = np.all((i >= 0) & (i < dims), axis=1)
        out = np.zeros(len(points), bool)
        k = np.ravel_multi_index(i[ok].T, dims)
        pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        out[ok] = keys[pos] == k
        return out

    return test


def _estimate(polytopes, boxes, samples, seed, weight):
    rng = np.random.default_rng(seed)
    lo = np.array([b[0] for b in boxes], np.float64)
    hi = np.array([b[1] for b in boxes], np.float64)
    bvol = np.prod(hi - lo, axis=1)
    share = np.maximum(64, np.round(samples * bvol / bvol.sum()).astype(int))
    est = np.zeros(2)
    var = np.zeros(2)
    for k, h in enumerate(polytopes):
        x = lo[k] + rng.random((share[k], 3)) * (hi[k] - lo[k])
        score = np.zeros((2, share[k]))
        ink = inside(h, x)
        if ink.any():
            xs = x[ink]
            mult = np.zeros(xs.shape[0])
            near = np.flatnonzero(np.all((lo <= xs.max(0)) & (hi >= xs.min(0)), axis=1))
            for j in near:
                mult += inside(polytopes[j], xs)
            score[0, ink] = 1.0 / mult
            if weight is not None:
                score[1, ink] = score[0, ink] * weight(xs)
        est += bvol[k] * score.mean(axis=1)
        var += bvol[k] ** 2 * score.var(axis=1, ddof=1) / share[k]
    return est, 1.96 * np.sqrt(var)


def union_volume(
    polytopes: list[np.ndarray],
    boxes: list[tuple[np.ndarray, np.ndarray]],
    samples: int = 200_000,
    seed: int = 0,
) -> tuple[float, float]:
    """(volume m^3, half-width of the 95% confidence interval m^3).

    ``polytopes``: half-plane arrays (H_k, 4); ``boxes``: (lo, hi) containing each polytope.
    ``samples`` points in total, spread in proportion to the box volumes.
    """
    est, ci = _estimate(polytopes, boxes, samples, seed, None)
    return float(est[0]), float(ci[0])


def union_waste(
    polytopes: list[np.ndarray],
    boxes: list[tuple[np.ndarray, np.ndarray]],
    occupied: Callable[[np.ndarray], np.ndarray],
    samples: int = 200_000,
    seed: int = 0,
) -> tuple[float, float, float, float]:
    """(Vol(union), its 95 % half-width, Vol(union \\ V+), its 95 % half-width), m^3, from one
    set of samples; ``occupied`` tests membership in V+ (:func:`in_voxels`)."""
    est, ci = _estimate(polytopes, boxes, samples, seed, lambda x: ~occupied(x))
    return float(est[0]), float(ci[0]), float(est[1]), float(ci[1])
