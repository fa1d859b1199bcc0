"""Random swarm scenarios on a :class:`~polycc.swarm.coverage.CoverageMap`: starts and ToI peaks at
free-cell centres (certified free at the grid's margin), pairwise apart."""

from __future__ import annotations

import numpy as np

from polycc.errors import PolyccError
from polycc.swarm.coverage import Targets


def spread_points(centres: np.ndarray, n: int, min_sep: float, rng: np.random.Generator, z_min: float = 0.3,
                  what: str = "drones") -> np.ndarray:
    """``n`` free-cell centres (z >= z_min) at least ``min_sep`` m apart, in random order."""
    cand = np.flatnonzero(centres[:, 2] >= z_min)
    out: list[int] = []
    for k in rng.permutation(cand):
        if all(np.linalg.norm(centres[k] - centres[j]) >= min_sep for j in out):
            out.append(int(k))
            if len(out) == n:
                return centres[out].copy()
    raise PolyccError(f"only {len(out)} free points {min_sep:g} m apart for {n} {what}; use fewer or a larger map")


def random_targets(centres: np.ndarray, k: int, rng: np.random.Generator, sigma: float = 0.4) -> Targets:
    """``k`` peaks at free cells >= 1 m apart, sigma ``sigma`` m, weight 1."""
    mu = spread_points(centres, k, 1.0, rng, what="targets")
    return Targets(mu, np.full(k, float(sigma)), np.ones(k))
