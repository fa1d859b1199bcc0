"""Exact ellipsoid–box intersection, with float error pushed toward "intersects".

PolyMerge Eq. (9): a box B meets the ellipsoid E = {p : |M (p - c)| <= 1} iff
``min_{p in B} |M (p - c)| <= 1``. Writing ``p = lo + sum_i t_i e_i (hi_i - lo_i)`` with
``t in [0, 1]^3`` turns this into a bounded least-squares problem

    min_t |w0 + T t|,   w0 = M (lo - c),   T = M diag(hi - lo),

whose minimiser lies in the relative interior of exactly one face of the cube (the
cube itself, one of 6 facets, 12 edges or 8 vertices). We evaluate, for every pair:

* the interior candidate: the centre clamped to the box,
* the 6 facet candidates: the 2-D unconstrained least-squares solution, clamped,
* the 12 edge candidates: the 1-D solution, clamped (this also covers the vertices).

Each candidate is a point of the box, so each value is an upper bound on the minimum,
and the true minimiser is among them (exact arithmetic), so their minimum is exact.

Float error. Every residual ``r = w0 + T t`` is a sum of a few float64 products. Its
rounding error is at most ``ERR_REL * (|M| |lo - c| + sum_i |T e_i|)`` where ERR_REL
is ~4500 machine epsilons, far above the true bound of a few tens. The test answers
"intersects" when ``min |r| - err <= 1``, so an ellipsoid that truly meets the box is
never reported as missing it. The facet solves use Gram–Schmidt (condition kappa, not
kappa^2 of normal equations), which keeps needle-thin ellipsoids accurate; an
inaccurate facet solution is still a point of the box, and the residual is flat along
the badly conditioned direction, so its value stays near the minimum.
"""

from __future__ import annotations

import numpy as np

ERR_REL = 1e-12

# Free axis and the two fixed axes of each of the 12 edges; fixed values in {0,1}^2.
_EDGES = [(a, b, c, tb, tc) for (a, b, c) in ((0, 1, 2), (1, 0, 2), (2, 0, 1))
          for tb in (0.0, 1.0) for tc in (0.0, 1.0)]
# Two free axes and the fixed axis of each of the 6 facets.
_FACETS = [(i, j, f, tf) for (i, j, f) in ((0, 1, 2), (0, 2, 1), (1, 2, 0)) for tf in (0.0, 1.0)]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(_dot(a, a))


def min_whitened_distance(c: np.ndarray, M: np.ndarray, lo: np.ndarray,
                          hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum over each box of |M (p - c)|, and a bound on its float error.

    c: (P, 3) ellipsoid centres; M: (P, 3, 3) whitening matrices; lo, hi: (P, 3) box
    corners (metres). Returns (dmin, err), both (P,) float64, with
    ``|dmin - true_min| <= err`` (``err`` is a generous bound, see module docstring).
    """
    c = np.asarray(c, np.float64)
    lo = np.asarray(lo, np.float64)
    ext = np.asarray(hi, np.float64) - lo
    d = lo - c
    w0 = np.einsum("pij,pj->pi", M, d)
    cols = [M[:, :, i] * ext[:, i : i + 1] for i in range(3)]  # T e_i, (P, 3) each
    col_norm = [_norm(m) for m in cols]
    err = ERR_REL * (np.sqrt(np.einsum("pij,pij->p", M, M)) * _norm(d) + col_norm[0] + col_norm[1] + col_norm[2] + 1.0)

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # Interior: the centre clamped to the box (t_c = (c - lo) / ext).
        tc = np.clip(np.nan_to_num(-d / ext, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
        r = w0 + tc[:, 0:1] * cols[0] + tc[:, 1:2] * cols[1] + tc[:, 2:3] * cols[2]
        best = _dot(r, r)

        for a, b, cc, tb, tcc in _EDGES:
            w = w0
            if tb:
                w = w + cols[b]
            if tcc:
                w = w + cols[cc]
            m = cols[a]
            t = np.clip(np.nan_to_num(-_dot(w, m) / _dot(m, m), nan=0.0), 0.0, 1.0)
            r = w + t[:, None] * m
            np.minimum(best, _dot(r, r), out=best)

        for i, j, f, tf in _FACETS:
            w = w0 + cols[f] if tf else w0
            mi, mj = cols[i], cols[j]
            # Gram–Schmidt: u = mi/|mi|, mj' = mj - (mj.u) u; solve for t_j then t_i.
            ni = col_norm[i]
            u = mi / ni[:, None]
            mjp = mj - _dot(mj, u)[:, None] * u
            tj = np.nan_to_num(-_dot(w, mjp) / _dot(mjp, mjp), nan=0.0)
            ti = np.nan_to_num(-_dot(w + tj[:, None] * mj, mi) / (ni * ni), nan=0.0)
            ti = np.clip(ti, 0.0, 1.0)
            tj = np.clip(tj, 0.0, 1.0)
            r = w + ti[:, None] * mi + tj[:, None] * mj
            np.minimum(best, _dot(r, r), out=best)

    return np.sqrt(best), err


def boxes_intersect(c: np.ndarray, M: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(P,) bool: box [lo, hi] meets ellipsoid {p : |M (p - c)| <= 1}; errs toward True."""
    dmin, err = min_whitened_distance(c, M, lo, hi)
    return dmin - err <= 1.0


def boxes_inside(c: np.ndarray, M: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(P,) bool: the whole box lies inside the ellipsoid (all 8 corners inside, with margin).

    Errs toward False, so a box reported inside truly is (the ellipsoid is convex).
    """
    c = np.asarray(c, np.float64)
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    ok = np.ones(c.shape[0], dtype=bool)
    scale = np.sqrt(np.einsum("pij,pij->p", M, M))
    for corner in range(8):
        p = np.where([(corner >> 0) & 1, (corner >> 1) & 1, (corner >> 2) & 1], hi, lo)
        d = p - c
        r = np.einsum("pij,pj->pi", M, d)
        ok &= _norm(r) + ERR_REL * (scale * _norm(d) + 1.0) <= 1.0
    return ok
