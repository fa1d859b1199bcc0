"""A certified lower bound of the on-board barrier psi (world frame, metres), 1-Lipschitz up to 1e-5.

For the stored scene (decoded float32 half-planes ``n . p <= d``, ``|n| <= 1``) let
``phi_k(p) = max_l (n_kl . p - d_kl)`` and ``c_k = min(log L_k, (L_k - 1)/e) / kappa``. Then

    B(p)  = -(1/kappa) log sum_k exp(-kappa (phi_k(p) - c_k))
    LB(p) = B(p) - r - 3 margin(p) - eps,   margin(p) = 2^-18 (|p|_1 + D + r + 32/kappa)

satisfies ``LB(p) <= psi(p)`` for the kernel's float32 psi (C and reference alike), at every p:

* each Boltzmann mean the kernel forms is over a subset of a polytope's planes that holds their
  maximum, so ``a_k >= phi_k - log(L')/kappa`` (entropy <= log L') and
  ``a_k >= phi_k - (L' - 1)/(e kappa)`` (each other term weighs <= exp(-kappa delta) and
  contributes <= 1/(e kappa)); both hold for the plane and polytope terms the kernel drops
  (dropping terms below the mean raises it) and for the polytopes it culls or aborts (removing a
  soft-min term raises the soft-min);
* so ``psi0 >= B`` exactly, and the float32 evaluation errs by less than ``2 margin(p) + eps``:
  4.01 u (|p|_1 + D) for each g (docs/barrier.md section 1), the sums and the exp/log
  approximations (relative 3e-7 per term: the ``eps`` terms in :func:`rounding_slack`), the final
  subtraction; the kernel then subtracts ``r + margin(p)`` itself.

``B`` is a soft-min of 1-Lipschitz functions (``|n| <= 1``), hence 1-Lipschitz; the margin terms add
``3 sqrt(3) 2^-18`` to the constant: :data:`LIP`. So ``LB(q) >= LB(p) - LIP |q - p|``: a value at one
point certifies a ball around it, which is how segments and grid cells are certified
(:func:`certify_segment`, :mod:`polycc.plan.grid`). Far polytopes may be replaced by a bound:
``phi_k(p) >= gamma_k (|p - c_k| - R_k)`` (the layout's culling constants, rounded outward), so
outside the ball of radius ``R_k + E / gamma_k`` the term is at most ``exp(-kappa (E - c_k))``.

tests/plan/test_certified.py checks ``LB <= psi`` against the float32 reference with hypothesis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from polycc.onboard.barrier import PSI_EMPTY
from polycc.onboard.layout import PackedScene

U32 = 2.0**-24
MARGIN_REL = 2.0**-18
LIP = 1.0 + 3.0 * math.sqrt(3.0) * MARGIN_REL  # Lipschitz constant of LB (B is 1-Lipschitz)
_EPS_ABS = 1e-6  # m: float64 evaluation of B and the kernel's conversions


def rounding_slack(kappa: float, l_max: int, n_polys: int) -> float:
    """The position-independent part of eps (m): float32 sums over <= l_max planes and n_polys
    polytopes and the exp/log approximations, each bounded by a relative error on terms of at
    most 20/kappa (the kernel keeps only terms within 17/kappa of the extreme; log L <= 5.6)."""
    return _EPS_ABS + U32 * ((4 * l_max + 64) * 40 + n_polys + 64) / kappa


@dataclass
class BarrierBound:
    """LB of one stored scene for agent radius ``radius`` (m) and sharpness ``kappa`` (1/m)."""

    packed: PackedScene
    kappa: float
    radius: float
    reach_e: float = 0.5  # m: E of the far-polytope bound (see :meth:`reach`)
    _h: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        sc = self.packed
        self.kappa = float(np.float32(self.kappa))
        self.radius = float(np.float32(self.radius))
        pm = sc.plane_matrix().astype(np.float64)
        polys = sc.polys
        self.first = polys["first"].astype(np.int64)
        self.count = polys["count"].astype(np.int64)
        # planes in polytope order (the layout keeps them contiguous; gathered anyway)
        cols = np.repeat(self.first - np.r_[0, np.cumsum(self.count)[:-1]], self.count) + np.arange(
            int(self.count.sum()))
        self.n = np.ascontiguousarray(pm[cols, :3].T)  # (3, P)
        self.d = pm[cols, 3].copy()
        self.first = np.r_[0, np.cumsum(self.count)[:-1]].astype(np.int64)
        L = self.count.astype(np.float64)
        self.c = np.minimum(np.log(np.maximum(L, 1.0)), (L - 1.0) / math.e) / self.kappa  # (K,)
        self.centre = np.stack([polys["cx"], polys["cy"], polys["cz"]], axis=1).astype(np.float64)
        self.r_out = polys["r_out"].astype(np.float64)
        self.inv_gamma = polys["inv_gamma"].astype(np.float64)
        self.coord_bound = float(sc.coord_bound)
        l_max = int(self.count.max()) if len(self.count) else 1
        self.slack = rounding_slack(self.kappa, l_max, sc.n_polys)
        self._h = pm

    @property
    def n_polys(self) -> int:
        return len(self.first)

    def reach(self, e: float | None = None) -> np.ndarray:
        """(K,) radii around the polytope centres outside which ``phi_k >= e`` (default reach_e)."""
        e = self.reach_e if e is None else e
        return self.r_out + max(e, 0.0) * self.inv_gamma

    def tail(self, e: float | None = None, polys: np.ndarray | None = None) -> float:
        """Upper bound of the soft-min sum of the polytopes ``polys`` (default all), scaled by
        ``exp(kappa e)``: each has ``phi_k >= e`` where it is replaced by the bound."""
        c = self.c if polys is None else self.c[polys]
        return float(np.sum(np.exp(self.kappa * c))) if len(c) else 0.0

    def margin(self, p: np.ndarray) -> np.ndarray:
        """The kernel's margin(p) in float64 (m)."""
        return MARGIN_REL * (np.abs(p).sum(axis=-1) + self.coord_bound + self.radius + 32.0 / self.kappa)

    def offset(self, p: np.ndarray) -> np.ndarray:
        """r + 3 margin(p) + eps: LB = B - offset."""
        return self.radius + 3.0 * self.margin(p) + self.slack

    def phi(self, p: np.ndarray, polys: np.ndarray | None = None) -> np.ndarray:
        """(M, K') exact max_l g_kl at points p (M, 3) for the polytopes ``polys`` (default all)."""
        p = np.asarray(p, np.float64).reshape(-1, 3)
        if polys is None:
            idx, n, d = np.arange(self.n_polys), self.n, self.d
            starts = self.first
        else:
            idx = np.asarray(polys, np.int64)
            if len(idx) == 0:
                return np.zeros((len(p), 0))
            cnt = self.count[idx]
            starts = np.r_[0, np.cumsum(cnt)[:-1]]
            cols = np.repeat(self.first[idx] - starts, cnt) + np.arange(int(cnt.sum()))
            n, d = self.n[:, cols], self.d[cols]
        if len(idx) == 0:
            return np.zeros((len(p), 0))
        out = np.empty((len(p), len(idx)))
        step = max(1, 4_000_000 // max(1, len(d)))
        for a in range(0, len(p), step):
            g = p[a:a + step] @ n - d
            out[a:a + step] = np.maximum.reduceat(g, starts, axis=1)
        return out

    def lower(self, p: np.ndarray, polys: np.ndarray | None = None, tail_e: float | None = None) -> np.ndarray:
        """LB at points p (M, 3), m. With ``polys``, only those polytopes are evaluated; the others
        must have ``phi >= tail_e`` at every p (the caller checks with :meth:`reach`) and enter
        through :meth:`tail`."""
        p = np.asarray(p, np.float64).reshape(-1, 3)
        if self.n_polys == 0:
            return np.full(len(p), float(PSI_EMPTY)) - self.offset(p)
        v = self.phi(p, polys) - (self.c if polys is None else self.c[np.asarray(polys, np.int64)])
        if polys is not None and len(v[0]) < self.n_polys:
            rest = np.setdiff1d(np.arange(self.n_polys), polys)
            v = np.concatenate([v, np.full((len(p), 1), float(tail_e))], axis=1)
            w = np.r_[np.ones(v.shape[1] - 1), self.tail(0.0, rest)]
        else:
            w = np.ones(v.shape[1])
        vmin = v.min(axis=1)
        s = np.exp(-self.kappa * (v - vmin[:, None])) @ w
        return vmin - np.log(s) / self.kappa - self.offset(p)


def near_segment(bound: BarrierBound, a: np.ndarray, b: np.ndarray, e: float) -> np.ndarray:
    """Polytopes whose ``phi < e`` region (inside the ball of :meth:`BarrierBound.reach`) can meet
    the segment a-b."""
    ab = b - a
    L2 = float(ab @ ab)
    t = np.clip(((bound.centre - a) @ ab) / L2, 0.0, 1.0) if L2 > 0 else np.zeros(bound.n_polys)
    dist = np.linalg.norm(bound.centre - (a + t[:, None] * ab), axis=1)
    return np.flatnonzero(dist < bound.reach(e) * (1 + 1e-9) + 1e-9)


@dataclass
class SegmentCheck:
    ok: bool
    lower: float  # certified lower bound of LB along the segment if ok, else the smallest LB found (m)
    evaluations: int


def certify_segment(bound: BarrierBound, a, b, req: float, min_half: float = 1e-4,
                    max_evaluations: int = 200_000, e: float | None = None, tight: float | None = None
                    ) -> SegmentCheck:
    """Is ``LB >= req`` on the whole segment a-b (m)? Certified by bisection: an interval of
    half-length h around a point with ``LB >= req + LIP h`` is accepted; a point with
    ``LB < req`` (or an interval shorter than ``2 min_half`` still undecided) rejects.

    With ``tight`` (m), intervals are accepted only once their bound is also within ``tight`` of
    the smallest LB seen, so ``lower`` is a certified bound within ``tight`` of the segment's
    minimum (for reporting clearance; costs more evaluations)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    length = float(np.linalg.norm(b - a))
    e = max(bound.reach_e, req + bound.radius + 0.1) if e is None else e
    polys = near_segment(bound, a, b, e)
    t0, t1 = np.array([0.0]), np.array([1.0])
    lowest = seen = math.inf
    evals = 0
    while len(t0):
        tm = 0.5 * (t0 + t1)
        half = 0.5 * (t1 - t0) * length
        v = bound.lower(a + tm[:, None] * (b - a), polys, e)
        evals += len(tm)
        if np.any(v < req):
            return SegmentCheck(False, float(v.min()), evals)
        seen = min(seen, float(v.min()))
        thr = req if tight is None else max(req, seen - tight)
        done = v - LIP * half >= thr
        if np.any(done):
            lowest = min(lowest, float(np.min(v[done] - LIP * half[done])))
        und = ~done
        if np.any(und & (half < min_half)) or evals > max_evaluations:
            return SegmentCheck(False, float(v[und].min()), evals)
        t0, t1, tm = t0[und], t1[und], tm[und]
        t0, t1 = np.r_[t0, tm], np.r_[tm, t1]
    return SegmentCheck(True, lowest, evals)
