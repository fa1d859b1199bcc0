"""Synthetic polytope scenes for tests and benchmarks (metres, world frame)."""

from __future__ import annotations

import numpy as np

from polycc.errors import PolyccError
from polycc.geometry.halfplanes import hull_halfplanes


def random_hull_polytopes(rng: np.random.Generator, n: int, *, extent=(10.0, 10.0, 3.0), size=(0.1, 0.6),
                          points=(8, 20)) -> list[np.ndarray]:
    """Synthetic obstacles: convex hulls of random points, scattered in a room [0, extent]."""
    lo, hi = size
    out = []
    for _ in range(n):
        c = rng.uniform(0.0, 1.0, 3) * np.asarray(extent)
        k = int(rng.integers(points[0], points[1] + 1))
        axes = rng.uniform(lo, hi, 3)
        out.append(hull_halfplanes(c + rng.normal(size=(k, 3)) * axes))
    return out


def pad_to_planes(polytopes: list[np.ndarray], total: int) -> list[np.ndarray]:
    """Append redundant half-planes (copies of a face moved 1 m outward) until the scene has
    exactly ``total`` half-planes; the polytopes themselves do not change."""
    out = [np.asarray(h, float).copy() for h in polytopes]
    have = sum(len(h) for h in out)
    if have > total:
        raise PolyccError(f"scene already has {have} > {total} half-planes")
    k = 0
    while have < total:
        h = out[k % len(out)]
        extra = h[0].copy()
        extra[3] += 1.0 + 0.01 * (have % 7)
        out[k % len(out)] = np.vstack([h, extra])
        have += 1
        k += 1
    return out
