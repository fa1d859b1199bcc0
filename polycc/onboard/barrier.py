"""float32 reference of the on-board barrier kernel (firmware_app/src/polycc_kernel.c).

Every float32 operation of the C is reproduced in the same order, vectorised across states
(the first axis) and sequential where the C is sequential (over polytopes and half-planes).
Results are bit-identical to the C built with ``-ffp-contract=off``; tests/test_kernel_bitexact.py
compares the uint32 patterns.  Derivations: docs/barrier.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from polycc.onboard.fastmath import ONE, F, exp32, log32
from polycc.onboard.layout import PackedScene

# Mirrors of the C macros (polycc_kernel.h).
NEGLIGIBLE_NATS = F(17.0)
POS_MAX = F(1.0e5)
KAPPA_MIN, KAPPA_MAX = F(1.0), F(1.0e4)
GRAD2_MIN = F("1.0e-12")
PSI_EMPTY = F(1.0e6)
MARGIN_REL = F(2.0**-18)
BIG = F("3.0e38")
ZERO = F(0.0)

FLAG_ACTIVE = 0x01
FLAG_INSIDE = 0x02
FLAG_INVALID = 0x04
FLAG_SATURATED = 0x08
FLAG_DEGENERATE = 0x10


@dataclass(frozen=True)
class Params:
    """Mirror of ``polycc_params_t`` (stored as float32)."""

    kappa: float = 100.0
    radius: float = 0.05
    beta: float = 1.0
    c_clf: float = 1.0
    v_max: float = 1.0

    def f32(self) -> tuple[np.float32, ...]:
        return tuple(F(v) for v in (self.kappa, self.radius, self.beta, self.c_clf, self.v_max))

    def valid(self) -> bool:
        k, r, b, c, v = self.f32()
        return bool(
            KAPPA_MIN <= k <= KAPPA_MAX and ZERO <= r <= POS_MAX and ZERO < b <= F(1e6) and ZERO <= c <= F(1e6)
            and ZERO < v <= F(1e3)
        )


def _finite(x: np.ndarray) -> np.ndarray:
    return (x.view(np.uint32) & np.uint32(0x7F800000)) != np.uint32(0x7F800000)


def _coord_ok(p: np.ndarray) -> np.ndarray:
    return np.all((p >= -POS_MAX) & (p <= POS_MAX), axis=1)


def _quantum_ok(q) -> bool:
    """Mirror of ``polycc_quantum_ok``: a power of two in [2^-20, 2^4]."""
    b = int(np.asarray(q, F).view(np.uint32))
    return (b & 0x007FFFFF) == 0 and 107 <= (b >> 23) <= 131


def _scene_ok(sc: PackedScene) -> bool:
    ok = bool((sc.n_polys == 0) == (sc.n_clusters == 0) and _quantum_ok(sc.quantum)
              and ZERO <= sc.coord_bound <= F(1e6) and ZERO <= sc.log_lmax <= F(12.0))
    if ok and sc.index is not None:
        r = sc.index.record()
        ok = bool(sc.n_polys > 0 and ZERO < r["cap"] <= F(1e6) and ZERO < r["inv_cell"] <= F(1e6)
                  and all(-POS_MAX <= r[k] <= POS_MAX for k in ("ox", "oy", "oz"))
                  and min(r["nx"], r["ny"], r["nz"]) > 0)
    return ok


def _visit_order(lead: np.ndarray, count: int) -> np.ndarray:
    """(8, count) plane order of the C per octant: the lead plane, then the others in order."""
    idx = np.arange(count)
    return np.array([np.r_[int(ld), idx[idx != int(ld)]] for ld in lead])


def _softmax_poly(H: np.ndarray, px, py, pz, kappa, neg_cut, abort_at):
    """Mirror of ``polycc_softmax_poly`` for the states given (1-D float32 arrays); H (n, L, 4)
    holds each state's half-planes in the order the C visits them (lead plane first).

    Returns (alive, a, ga): alive[i] is False where the C returns 0 (polytope dropped).
    """
    nx, ny, nz, d = (H[:, :, j] for j in range(4))
    g = ((nx * px[:, None] + ny * py[:, None]) + nz * pz[:, None]) - d  # (n, L): same ops per element
    m = g[:, 0].copy()
    alive = ~(m >= abort_at)
    thr = m + neg_cut
    n = len(px)
    n_exp = np.zeros(n, np.int64)  # planes that took the exp path (statistics only)
    S = np.ones(n, F)
    A = np.zeros(n, F)
    N = H[:, 0, :3].copy()
    M = np.zeros((n, 3), F)
    for l in range(1, H.shape[1]):
        gl = g[:, l]
        sel = alive & (gl > thr)
        if not sel.any():
            continue
        n_exp += sel
        new = sel & (gl > m)
        drop = new & (gl >= abort_at)
        alive &= ~drop
        new &= ~drop
        acc = sel & ~(gl > m)
        nl = H[:, l, :3]
        if new.any():
            i = np.nonzero(new)[0]
            d0 = m[i] - gl[i]
            r = exp32(kappa * d0)
            A[i] = r * (A[i] + d0 * S[i])
            M[i] = r[:, None] * (M[i] + d0[:, None] * N[i])
            S[i] = r * S[i] + ONE
            N[i] = r[:, None] * N[i] + nl[i]
            m[i] = gl[i]
            thr[i] = m[i] + neg_cut
        if acc.any():
            i = np.nonzero(acc)[0]
            dd = gl[i] - m[i]
            e = exp32(kappa * dd)
            ed = e * dd
            S[i] = S[i] + e
            A[i] = A[i] + ed
            N[i] = N[i] + e[:, None] * nl[i]
            M[i] = M[i] + ed[:, None] * nl[i]
    invS = ONE / S
    q = A * invS
    a = m + q
    ga = (N + kappa * (M - q[:, None] * N)) * invS[:, None]
    return alive, a, ga, n_exp


def barrier(scene: PackedScene, params: Params, p: np.ndarray, *, cull: bool = True, stats: dict | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mirror of ``polycc_barrier`` for states p (n, 3): returns psi (n,), grad (n, 3), flags (n,).

    ``cull=False`` (not in the C) evaluates every polytope fully: the tests use it to check
    that culling changes psi by less than the bound of docs/barrier.md.  If ``stats`` is a dict,
    it receives per state ``"evaluated"`` (polytopes in the soft-min), ``"entered"``
    (polytopes that passed the sphere tests, some then dropped by their lead plane) and
    ``"exp_planes"`` (half-planes that took the soft-max's exp path: a new maximum or a term)."""
    p = np.ascontiguousarray(np.asarray(p, dtype=F).reshape(-1, 3))
    n = p.shape[0]
    psi = np.zeros(n, F)
    grad = np.zeros((n, 3), F)
    flags = np.zeros(n, np.uint32)
    with np.errstate(all="ignore"):
        valid = _coord_ok(p) if (params.valid() and _scene_ok(scene)) else np.zeros(n, bool)
        flags[~valid] = FLAG_INVALID
        vi = np.nonzero(valid)[0]
        if len(vi):
            psi[vi], grad[vi], bad, nev, (entered, exp_planes) = _barrier_valid(scene, params, p[vi], cull)
            if stats is not None:
                stats["evaluated"] = np.zeros(n, np.int64)
                stats["evaluated"][vi] = nev
                stats["entered"] = np.zeros(n, np.int64)
                stats["entered"][vi] = entered
                stats["exp_planes"] = np.zeros(n, np.int64)
                stats["exp_planes"][vi] = exp_planes
            flags[vi[bad]] = FLAG_INVALID
    return psi, grad, flags


def _barrier_valid(scene: PackedScene, params: Params, p: np.ndarray, cull: bool):
    kappa, radius = params.f32()[:2]
    px, py, pz = p[:, 0], p[:, 1], p[:, 2]
    n = len(px)
    invk = ONE / kappa
    neg_cut = -NEGLIGIBLE_NATS * invk
    slack = (NEGLIGIBLE_NATS + scene.log_lmax) * invk
    polys, clusters = scene.polys, scene.clusters
    pm = scene.plane_matrix()

    def d2_of(rec, idx):
        ux, uy, uz = px[idx] - F(rec["cx"]), py[idx] - F(rec["cy"]), pz[idx] - F(rec["cz"])
        return (ux * ux + uy * uy) + uz * uz

    def culled(rec, idx, T):
        Tp = np.where(T > ZERO, T, ZERO)
        rad = F(rec["r_out"]) + Tp * F(rec["inv_gamma"])
        return d2_of(rec, idx) > rad * rad

    everyone = np.arange(n)
    a_ref = np.full(n, BIG, F)
    cur = np.zeros(n, F)
    S2 = np.zeros(n, F)
    G = np.zeros((n, 3), F)
    nev = np.zeros(n, np.int64)
    entered = np.zeros(n, np.int64)  # polytopes that passed the sphere tests (statistics only)
    exp_planes = np.zeros(n, np.int64)  # half-planes on the soft-max's exp path (statistics only)

    def threshold(idx):
        lim = np.where((nev[idx] != 0) & (cur[idx] < a_ref[idx]), cur[idx], a_ref[idx])
        return lim + slack if cull else np.full(len(idx), np.inf, F)

    def aref_step(P, idx):
        d2 = d2_of(P, idx)
        t = a_ref[idx] + F(P["r_in"])
        upd = (t > ZERO) & (d2 < t * t)
        a_ref[idx[upd]] = np.sqrt(d2[upd]) - F(P["r_in"])

    def visit(P, open_):
        T = threshold(open_)
        keep = ~culled(P, open_, T)
        i, T = open_[keep], T[keep]
        if len(i) == 0:
            return
        entered[i] += 1
        h = pm[int(P["first"]) : int(P["first"]) + int(P["count"])]
        ux, uy, uz = px[i] - F(P["cx"]), py[i] - F(P["cy"]), pz[i] - F(P["cz"])
        octant = np.signbit(ux) * 1 + np.signbit(uy) * 2 + np.signbit(uz) * 4
        H = h[_visit_order(P["lead"], len(h))[octant]]
        alive, a, ga, n_exp = _softmax_poly(H, px[i], py[i], pz[i], kappa, neg_cut, T)
        exp_planes[i] += n_exp
        i, a, ga = i[alive], a[alive], ga[alive]
        _softmin_update(i, a, ga, kappa, cur, S2, G, nev)

    if scene.index is not None:
        lid, _ = scene.index_leaf(p)
        lists = scene.index.lists()
        for L in np.unique(lid[lid >= 0]):
            idx = np.nonzero(lid == L)[0]
            for k in lists[L]:
                aref_step(polys[int(k)], idx)
            for k in lists[L]:
                visit(polys[int(k)], idx)
    else:
        for C in clusters:
            t = a_ref + F(C["r_in"])
            idx = np.nonzero((t > ZERO) & (d2_of(C, everyone) < t * t))[0]
            for P in polys[int(C["first"]) : int(C["first"]) + int(C["count"])]:
                if len(idx) == 0:
                    break
                aref_step(P, idx)
        for C in clusters:
            open_ = everyone[~culled(C, everyone, threshold(everyone))]
            for P in polys[int(C["first"]) : int(C["first"]) + int(C["count"])]:
                if len(open_) == 0:
                    break
                visit(P, open_)

    marg = MARGIN_REL * (((((np.abs(px) + np.abs(py)) + np.abs(pz)) + scene.coord_bound) + radius) + F(32.0) * invk)
    psi0 = np.full(n, PSI_EMPTY, F)
    grad = np.zeros((n, 3), F)
    e = np.nonzero(nev != 0)[0]
    invS2 = ONE / S2[e]
    psi0[e] = cur[e] - log32(S2[e]) * invk
    grad[e] = G[e] * invS2[:, None]
    if scene.index is not None:  # clearance cap: psi0' = min(psi0, D) with no gradient
        capped = ~(psi0 < scene.index.cap)
        psi0[capped] = scene.index.cap
        grad[capped] = ZERO
    psi = (psi0 - (radius + marg)).astype(F)
    bad = ~(_finite(psi) & np.all(_finite(grad), axis=1))
    psi[bad] = ZERO
    grad[bad] = ZERO
    return psi, grad, bad, nev, (entered, exp_planes)


def _softmin_update(i, a, ga, kappa, cur, S2, G, nev) -> None:
    """Online soft-min step of ``polycc_barrier`` for the states i (in place)."""
    c, sg = cur[i], S2[i]
    fst = nev[i] == 0
    lt = ~fst & (a < c)
    ge = ~fst & ~(a < c)
    new_c, new_s, new_g = c.copy(), sg.copy(), G[i].copy()
    new_c[fst], new_s[fst], new_g[fst] = a[fst], ONE, ga[fst]
    if lt.any():
        r = exp32(kappa * (a[lt] - c[lt]))
        new_s[lt] = r * sg[lt] + ONE
        new_g[lt] = r[:, None] * G[i[lt]] + ga[lt]
        new_c[lt] = a[lt]
    if ge.any():
        x = kappa * (c[ge] - a[ge])
        take = x > -NEGLIGIBLE_NATS
        j = np.nonzero(ge)[0][take]
        e = exp32(x[take])
        new_s[j] = sg[j] + e
        new_g[j] = G[i[j]] + e[:, None] * ga[j]
    cur[i], S2[i], G[i] = new_c, new_s, new_g
    nev[i] += 1


def _saturate(v: np.ndarray, vmax: np.float32) -> np.ndarray:
    """Mirror of ``polycc_saturate`` in place on rows of v; returns the rows it scaled."""
    n2 = (v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]) + v[:, 2] * v[:, 2]
    sat = n2 > vmax * vmax
    if sat.any():
        s = vmax / np.sqrt(n2[sat])
        v[sat] = v[sat] * s[:, None]
    return sat


def saturate(u: np.ndarray, vmax) -> bool:
    """Mirror of ``polycc_saturate`` on one float32 vector (3,), in place; True if it scaled it."""
    rows = u.reshape(1, 3).copy()
    sat = bool(_saturate(rows, F(vmax))[0])
    u[:] = rows[0]
    return sat


def step(scene: PackedScene, params: Params, x: np.ndarray, goal: np.ndarray) -> dict[str, np.ndarray]:
    """Mirror of ``polycc_step`` for states x (n, 3) and goals (n, 3) or (3,).

    Returns a dict of float32 arrays u (n,3), u_nom (n,3), psi (n,), grad (n,3) and uint32 flags.
    """
    x = np.ascontiguousarray(np.asarray(x, dtype=F).reshape(-1, 3))
    n = x.shape[0]
    goal = np.broadcast_to(np.asarray(goal, dtype=F).reshape(-1, 3), (n, 3)).astype(F)
    _, _, beta, c_clf, v_max = params.f32()
    with np.errstate(all="ignore"):
        psi, grad, flags = barrier(scene, params, x)
        goal_bad = ~_coord_ok(goal)
        flags[goal_bad] = FLAG_INVALID
        psi[goal_bad] = ZERO
        grad[goal_bad] = ZERO
        ok = flags == 0
        h = F(-0.5) * c_clf
        u_nom = h * (x - goal)
        flags[ok & _saturate(u_nom, v_max)] |= FLAG_SATURATED
        dot = (grad[:, 0] * u_nom[:, 0] + grad[:, 1] * u_nom[:, 1]) + grad[:, 2] * u_nom[:, 2]
        viol = dot + beta * psi
        u = u_nom.copy()
        act = ok & (viol < ZERO)
        g2 = (grad[:, 0] * grad[:, 0] + grad[:, 1] * grad[:, 1]) + grad[:, 2] * grad[:, 2]
        degen = act & ~(g2 >= GRAD2_MIN)
        act &= ~degen
        lam = -viol[act] / g2[act]
        u[act] = u[act] + lam[:, None] * grad[act]
        flags[act] |= FLAG_ACTIVE
        uu = u[act]
        if act.any():
            sat_rows = _saturate(uu, v_max)
            u[act] = uu
            flags[np.nonzero(act)[0][sat_rows]] |= FLAG_SATURATED
        flags[ok & (psi < ZERO)] |= FLAG_INSIDE
        fin = np.all(_finite(u) & _finite(u_nom), axis=1)
        zero = ~ok | degen | ~fin
        u[zero] = ZERO
        u_nom[zero] = ZERO
        psi[zero] = ZERO
        grad[zero] = ZERO
        flags[ok & ~fin] = FLAG_INVALID
        flags[degen] = FLAG_INVALID | FLAG_DEGENERATE
    return {"u": u, "u_nom": u_nom, "psi": psi, "grad": grad, "flags": flags}


def exact_minmax(scene: PackedScene, p: np.ndarray) -> np.ndarray:
    """min_k max_l (n_kl . p - d_kl) in float64 over the stored float32 half-planes (the
    right-hand side of the certified inequality psi + r <= min max)."""
    p = np.asarray(p, np.float64).reshape(-1, 3)
    best = np.full(len(p), np.inf)
    for h in scene.polytopes():
        h = h.astype(np.float64)
        best = np.minimum(best, np.max(p @ h[:, :3].T - h[:, 3], axis=1))
    return best
