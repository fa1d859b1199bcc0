"""Synthetic polytope scenes for tests and benchmarks (metres, world frame)."""

from __future__ import annotations

import numpy as np

from polycc.errors import PolyccError
from polycc.geometry.halfplanes import axis_box, hull_halfplanes
from polycc.onboard.layout import PackedScene, pack_scene


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


def small_scene(seed: int, n: int, boxes: bool) -> PackedScene:
    """n random axis boxes (0.05-1.5 m sides) or convex hulls (5-25 points) in [0, 4 m]^3, packed."""
    rng = np.random.default_rng(seed)
    if boxes:
        polys = []
        for _ in range(n):
            lo = rng.uniform(0, 4, 3)
            polys.append(axis_box(lo, lo + rng.uniform(0.05, 1.5, 3)))
    else:
        polys = random_hull_polytopes(rng, n, extent=(4.0, 4.0, 4.0), size=(0.05, 1.0), points=(5, 25))
    return pack_scene(polys)


def shell_scene(sc: PackedScene, dist: float = 0.5) -> PackedScene:
    """The same polytopes translated onto a shell around the origin so that max_l g_kl(0) = dist (m)
    for every k: all lie within the culling distance of the origin (the kernel's worst case)."""
    k = sc.n_polys
    i = np.arange(k) + 0.5
    phi, th = np.arccos(1 - 2 * i / k), np.pi * (1 + 5 ** 0.5) * i
    dirs = np.c_[np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)]
    out = []
    for h, u, P in zip(sc.polytopes(), dirs, sc.polys):
        h = h.astype(np.float64)
        c = np.array([P["cx"], P["cy"], P["cz"]], np.float64)
        lo, hi = 0.0, 50.0
        for _ in range(60):  # bisect the shift s along u with max_l g_l(0) = dist
            mid = 0.5 * (lo + hi)
            val = np.max(-(h[:, 3] + h[:, :3] @ (mid * u - c)))
            lo, hi = (mid, hi) if val < dist else (lo, mid)
        t = hi * u - c
        out.append(np.c_[h[:, :3], h[:, 3] + h[:, :3] @ t])
    return pack_scene(out, merge_duplicates=False)
