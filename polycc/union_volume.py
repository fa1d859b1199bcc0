"""Monte Carlo volume of a union of convex polytopes, with a confidence interval.

Estimator: for each polytope k, draw points uniformly in its bounding box B_k and score
``1[x in P_k] / m(x)`` with m(x) the number of polytopes containing x. Summed over k,
``sum_k Vol(B_k) * mean(score_k)`` is an unbiased estimate of Vol(union) (each point of
the union is counted once in total), and the per-polytope sample variances give the
standard error. Used for conservativeness = Vol(union) / Vol(V+).
"""

from __future__ import annotations

import numpy as np


def inside(h: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points p (M, 3) in {x : n . x <= d} for rows h (H, 4)."""
    return np.all(p @ h[:, :3].T <= h[:, 3], axis=1)


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
    rng = np.random.default_rng(seed)
    lo = np.array([b[0] for b in boxes], np.float64)
    hi = np.array([b[1] for b in boxes], np.float64)
    bvol = np.prod(hi - lo, axis=1)
    share = np.maximum(64, np.round(samples * bvol / bvol.sum()).astype(int))
    est, var = 0.0, 0.0
    for k, h in enumerate(polytopes):
        x = lo[k] + rng.random((share[k], 3)) * (hi[k] - lo[k])
        score = np.zeros(share[k])
        ink = inside(h, x)
        if ink.any():
            xs = x[ink]
            mult = np.zeros(xs.shape[0])
            near = np.flatnonzero(np.all((lo <= xs.max(0)) & (hi >= xs.min(0)), axis=1))
            for j in near:
                mult += inside(polytopes[j], xs)
            score[ink] = 1.0 / mult
        est += bvol[k] * score.mean()
        var += bvol[k] ** 2 * score.var(ddof=1) / share[k]
    return est, 1.96 * float(np.sqrt(var))
