"""float32 mirror of ``firmware_app/src/polycc_swarm.c``: neighbour terms (buffered Voronoi
half-spaces with an ageing buffer) soft-min combined with the kernel's obstacle barrier.

Every operation in the C order, on float32 scalars, so results are bit-identical to the C built with
``-ffp-contract=off`` (tests/onboard/test_swarm_bitexact.py).  Metres, seconds, world frame;
derivation and assumptions: docs/swarm.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from polycc.onboard import barrier as B
from polycc.onboard.fastmath import exp32, log32

F = np.float32
MAX = 16  # POLYCC_SWARM_MAX
TIMEOUT_MS = 500  # POLYCC_SWARM_TIMEOUT_MS
AGE_MAX_MS = 60000  # POLYCC_SWARM_AGE_MAX_MS
RADIUS_MAX = F(10.0)  # POLYCC_SWARM_RADIUS_MAX
V_MAX = F(100.0)  # POLYCC_SWARM_V_MAX
ONE_MINUS = F(0.99999904632568359375)  # 1 - 2^-20
MARGIN = F(2.0 ** -18)
FLOOR = F(2.0 ** -10)
D2_MIN = F("1e-12")
POS_MAX = F(1.0e5)  # POLYCC_POS_MAX
NEGLIGIBLE = F(17.0)
GRAD2_MIN = F("1e-12")


def _fin(x) -> bool:
    return bool(np.isfinite(F(x)))


def _coord_ok(v) -> bool:
    v = F(v)
    return _fin(v) and -POS_MAX <= v <= POS_MAX


@dataclass
class Neighbour:
    n: np.ndarray  # (3,) float32, |n| <= 1
    a: np.float32  # n . p0, m
    b: np.float32  # lower bound of n . p_j, m
    r: np.float32  # radius, m
    age_ms: int
    id: int


@dataclass
class Swarm:
    """The neighbour table (``polycc_swarm_t``): slot k -> Neighbour or None."""

    slots: list = field(default_factory=lambda: [None] * MAX)

    @property
    def count(self) -> int:
        return sum(s is not None for s in self.slots)

    def report(self, nid: int, p_j, age_ms: int, r_j: float, p0) -> int:
        """Mirror of ``polycc_swarm_report``; returns the slot or -1."""
        p_j = np.asarray(p_j, F).reshape(3)
        p0 = np.asarray(p0, F).reshape(3)
        r_j = F(r_j)
        if not all(_coord_ok(v) for v in p_j) or not all(_coord_ok(v) for v in p0):
            return -1
        if not _fin(r_j) or not (r_j >= F(0)) or not (r_j <= RADIUS_MAX):
            return -1
        k = next((i for i, s in enumerate(self.slots) if s is not None and s.id == nid), -1)
        if k < 0:
            k = next((i for i, s in enumerate(self.slots) if s is None), -1)
            if k < 0:
                return -1
        d = p_j - p0
        d2 = (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]
        if not (d2 >= D2_MIN):
            n = np.zeros(3, F)
        else:
            s = (F(1.0) / np.sqrt(d2)) * ONE_MINUS
            n = (d * s).astype(F)
        a = (n[0] * p0[0] + n[1] * p0[1]) + n[2] * p0[2]
        p1 = (abs(p_j[0]) + abs(p_j[1])) + abs(p_j[2])
        b = ((n[0] * p_j[0] + n[1] * p_j[1]) + n[2] * p_j[2]) - MARGIN * (p1 + FLOOR)
        self.slots[k] = Neighbour(n, F(a), F(b), r_j, min(int(age_ms), AGE_MAX_MS), int(nid))
        return k

    def forget(self, nid: int) -> bool:
        """Mirror of ``polycc_swarm_forget``."""
        for k, s in enumerate(self.slots):
            if s is not None and s.id == nid:
                self.slots[k] = None
                return True
        return False

    def age(self, dt_ms: int) -> None:
        for s in self.slots:
            if s is not None:
                s.age_ms = AGE_MAX_MS if AGE_MAX_MS - s.age_ms < dt_ms else s.age_ms + int(dt_ms)

    def stale(self, timeout_ms: int = TIMEOUT_MS) -> bool:
        return any(s is not None and s.age_ms > timeout_ms for s in self.slots)


def term(nb: Neighbour, r, v, p) -> tuple[np.float32, bool]:
    """Mirror of ``polycc_swarm_term``: (h_j(p), ageing branch)."""
    r, v = F(r), F(v)
    p = np.asarray(p, F).reshape(3)
    rho = r + nb.r
    tau = F(nb.age_ms) * F(0.001)
    vt = v * tau
    fair = F(0.5) * ((nb.a + nb.b) - rho)
    aged = (nb.b - rho) - vt
    ag = bool(aged < fair)
    e = aged if ag else fair
    n = nb.n
    np_ = (n[0] * p[0] + n[1] * p[1]) + n[2] * p[2]
    p1 = (abs(p[0]) + abs(p[1])) + abs(p[2])
    mu = MARGIN * ((((p1 + abs(nb.b)) + rho) + vt) + (abs(e) + FLOOR))
    return F((e - np_) - mu), ag



def _zero(flags: int) -> dict:
    z = np.zeros(3, F)
    return {"u": z.copy(), "u_nom": z.copy(), "psi": F(0), "grad": z.copy(), "flags": np.uint32(flags)}


def step(scene, params: B.Params, sw: Swarm, v_nbr, x, goal) -> dict:
    """Mirror of ``polycc_swarm_step`` for one state: dict u, u_nom, psi, grad (float32), flags."""
    x = np.asarray(x, F).reshape(3)
    goal = np.asarray(goal, F).reshape(3)
    with np.errstate(all="ignore"):
        k = B.step(scene, params, x[None], goal[None])
        out = {"u": k["u"][0].copy(), "u_nom": k["u_nom"][0].copy(), "psi": F(k["psi"][0]),
               "grad": k["grad"][0].copy(), "flags": np.uint32(k["flags"][0])}
        if sw.count == 0 or out["flags"] & B.FLAG_INVALID:
            return out
        v = F(v_nbr)
        if not _fin(v) or not (v >= F(0)) or not (v <= V_MAX):
            return _zero(B.FLAG_INVALID)
        kappa, radius, beta, c_clf, v_max = params.f32()
        flags = 0
        h = F(-0.5) * c_clf
        un = (h * (x - goal)).astype(F)
        if B.saturate(un, v_max):
            flags |= B.FLAG_SATURATED
        c = out["psi"]
        S = F(1.0)
        G = out["grad"].copy()
        Dacc = F(0.0)
        for nb in sw.slots:
            if nb is None:
                continue
            hj, ag = term(nb, radius, v, x)
            dv = v if ag else F(0.0)
            if hj < c:
                r = exp32(np.array([kappa * (hj - c)], F))[0]
                S = r * S + F(1.0)
                G = (r * G + -nb.n).astype(F)
                Dacc = r * Dacc + dv
                c = hj
            else:
                xx = kappa * (c - hj)
                if xx > -NEGLIGIBLE:
                    e = exp32(np.array([xx], F))[0]
                    S = S + e
                    G = (G + e * -nb.n).astype(F)
                    Dacc = Dacc + e * dv
        psi = F(c - log32(np.array([S], F))[0] / kappa)
        invS = F(1.0) / S
        grad = (G * invS).astype(F)
        D = Dacc * invS
        u = un.copy()
        dot = (grad[0] * un[0] + grad[1] * un[1]) + grad[2] * un[2]
        viol = (dot + beta * psi) - D
        if viol < F(0):
            g2 = (grad[0] * grad[0] + grad[1] * grad[1]) + grad[2] * grad[2]
            if not (g2 >= GRAD2_MIN):
                return _zero(B.FLAG_INVALID | B.FLAG_DEGENERATE)
            lam = -viol / g2
            u = (u + lam * grad).astype(F)
            flags |= B.FLAG_ACTIVE
            if B.saturate(u, v_max):
                flags |= B.FLAG_SATURATED
        if psi < F(0):
            flags |= B.FLAG_INSIDE
        if not _fin(psi) or not (np.all(np.isfinite(u)) and np.all(np.isfinite(grad))):
            return _zero(B.FLAG_INVALID)
        return {"u": u, "u_nom": un, "psi": psi, "grad": grad, "flags": np.uint32(flags)}
