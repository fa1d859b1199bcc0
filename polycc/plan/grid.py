"""The planning grid: cells (world frame, metres) whose whole closed cube is certified free.

Cell ``(i, j, k)`` is the cube of side ``spacing`` centred on ``lo + (i + 1/2, j + 1/2, k + 1/2) spacing``.
:func:`lower_field` gives, per cell centre, a value ``F <= LB`` (:mod:`polycc.plan.certified`):
every polytope is evaluated exactly on the cells inside the ball where its ``phi`` can be below
``E`` and bounded by ``exp(-kappa (E - c_k))`` elsewhere (both terms counted everywhere, which can
only lower F). A cell is *free* when ``F >= margin + LIP spacing sqrt(3)/2``: then ``LB >= margin``
on the whole cube, so any polyline through free cells (grid moves between neighbours, or a
straight line whose cells are all free) keeps ``psi >= margin`` and its ``margin``-tube
``psi >= 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from polycc.geometry.halfplanes import polytope_vertices
from polycc.plan.certified import LIP, BarrierBound


@dataclass
class Grid:
    """The free-cell grid of one (scene, radius, margin, spacing, bounds)."""

    lo: np.ndarray  # (3,) m, corner of cell (0, 0, 0)
    spacing: float  # m
    shape: tuple[int, int, int]
    field: np.ndarray  # float32 (nx, ny, nz): F, a lower bound of LB at the cell centres, m (capped)
    margin: float  # m
    cap: float  # m: F values are only certain up to here (above: "at least cap")

    @property
    def need(self) -> float:
        """F a cell needs to be free (m)."""
        return self.margin + LIP * self.spacing * math.sqrt(3.0) / 2.0 + 1e-9

    @property
    def free(self) -> np.ndarray:
        return self.field >= self.need

    @property
    def hi(self) -> np.ndarray:
        return self.lo + self.spacing * np.asarray(self.shape)

    def centres(self, idx: np.ndarray) -> np.ndarray:
        return self.lo + (np.asarray(idx, np.float64) + 0.5) * self.spacing

    def cell_of(self, p: np.ndarray) -> np.ndarray:
        """(…, 3) integer cell of points p (clipped into the grid)."""
        ijk = np.floor((np.asarray(p, np.float64) - self.lo) / self.spacing).astype(np.int64)
        return np.clip(ijk, 0, np.asarray(self.shape) - 1)

    def flat(self, ijk: np.ndarray) -> np.ndarray:
        ijk = np.asarray(ijk, np.int64)
        return (ijk[..., 0] * self.shape[1] + ijk[..., 1]) * self.shape[2] + ijk[..., 2]

    def unflat(self, f: np.ndarray) -> np.ndarray:
        return np.stack(np.unravel_index(np.asarray(f, np.int64), self.shape), axis=-1)

    def segment_lower(self, a: np.ndarray, b: np.ndarray) -> float:
        """A certified lower bound of LB on the segment a-b from the field alone: the segment in
        pieces of at most spacing/2, each bounded by the F of the cell holding its midpoint minus
        LIP times the largest distance from that cell's centre (at one of the piece's ends)."""
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        length = float(np.linalg.norm(b - a))
        n = max(1, int(math.ceil(length / (0.5 * self.spacing))))
        t = np.arange(n + 1) / n
        ends = a + t[:, None] * (b - a)
        mid = 0.5 * (ends[:-1] + ends[1:])
        ijk = self.cell_of(mid)
        c = self.centres(ijk)
        dist = np.maximum(np.linalg.norm(ends[:-1] - c, axis=1), np.linalg.norm(ends[1:] - c, axis=1))
        f = self.field[ijk[:, 0], ijk[:, 1], ijk[:, 2]].astype(np.float64)
        inside = np.all((ends >= self.lo) & (ends <= self.hi), axis=1)
        if not inside.all():
            return -math.inf
        return float(np.min(f - LIP * dist))


def field_reach(bound: BarrierBound, need: float) -> float:
    """E for the field: far cells (every phi >= E) get F >= need + 5 cm."""
    log_tail = math.log(max(bound.tail(0.0), 1.0)) / bound.kappa
    return need + bound.radius + log_tail + 0.05 + 1e-3


def poly_blocks(bound: BarrierBound, lo: np.ndarray, spacing: float, shape, e: float) -> np.ndarray:
    """(K, 6) cell-index ranges [i0, i1, j0, j1, k0, k1) holding every cell centre where
    ``phi_k < e``: the bounding box of the polytope with every plane moved out by e (vertices by
    qhull, one cell added for its rounding), cut to the ball of :meth:`BarrierBound.reach`."""
    lo = np.asarray(lo, np.float64)
    hi_idx = np.asarray(shape, np.int64)
    out = np.zeros((bound.n_polys, 6), np.int64)
    reach = bound.reach(e)
    for k in range(bound.n_polys):
        c = bound.centre[k]
        blo, bhi = c - reach[k], c + reach[k]
        a, n = bound.first[k], bound.count[k]
        h = np.c_[bound.n[:, a:a + n].T, bound.d[a:a + n] + e]
        v = polytope_vertices(h, c)
        if v is not None:
            blo, bhi = np.maximum(blo, v.min(0) - spacing), np.minimum(bhi, v.max(0) + spacing)
        i0 = np.clip(np.floor((blo - lo) / spacing - 0.5).astype(np.int64), 0, hi_idx)
        i1 = np.clip(np.ceil((bhi - lo) / spacing - 0.5).astype(np.int64) + 1, 0, hi_idx)
        out[k] = np.maximum([i0[0], i1[0], i0[1], i1[1], i0[2], i1[2]], 0)
    return out


def lower_field(bound: BarrierBound, lo: np.ndarray, spacing: float, shape: tuple[int, int, int], e: float
                ) -> np.ndarray:
    """F (float32, ``shape``) at the cell centres: a lower bound of LB (see module docstring)."""
    from polycc.plan.native import field_sums

    lo = np.asarray(lo, np.float64)
    vmin = np.full(shape, e, np.float64)  # running min of phi_k - c_k, starting at the far bound
    ssum = np.full(shape, bound.tail(0.0), np.float64)  # the far bound of every polytope, counted everywhere
    if bound.n_polys:
        planes = np.c_[bound.n.T, bound.d]
        field_sums(planes, bound.first, bound.count, bound.c, poly_blocks(bound, lo, spacing, shape, e),
                   bound.centre, bound.reach(e), lo, spacing, bound.kappa, e, vmin, ssum)
    out = np.empty(shape, np.float32)
    nx, ny, nz = shape
    ys = lo[1] + (np.arange(ny) + 0.5) * spacing
    zs = lo[2] + (np.arange(nz) + 0.5) * spacing
    for i in range(nx):  # the offset depends on |p|_1 (the kernel's margin): one x-slab at a time
        x = lo[0] + (i + 0.5) * spacing
        pts = np.stack(np.broadcast_arrays(x, ys[:, None], zs[None, :]), axis=-1)
        f = vmin[i] - np.log(ssum[i]) / bound.kappa - bound.offset(pts)
        f32 = f.astype(np.float32)  # rounded toward -inf, so F stays a lower bound
        out[i] = np.where(f32.astype(np.float64) > f, np.nextafter(f32, np.float32(-np.inf)), f32)
    return out
