"""float32 reference of the shield (firmware_app/src/polycc_shield.c), bit-exact with the C.

Velocity-aware backup CBF on the certified barrier psi (docs/barrier.md, section 8).  World frame,
z up; metres, seconds, m/s, m/s^2.  Every float32 operation of the C is reproduced in the same
order on numpy float32 scalars; psi comes from :func:`polycc.onboard.barrier.barrier`, the kernel's
own mirror.  :func:`run` returns what ``polycc_shield_run`` leaves in its job.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from polycc.onboard import barrier as B
from polycc.onboard.fastmath import F
from polycc.onboard.layout import PackedScene

MAX_STEPS = 200
MAX_EVALS = 32
VA_MAX = F(100.0)
LEN_SLACK = F("1.0e-4")

CERTIFIED = 0x01
ACTIVE = 0x02
INFEASIBLE = 0x04
INVALID = 0x08
NO_STOP = 0x10
BLOCKED = 0x20
EVAL_CAP = 0x40
DONE = 0x80
SATURATED = 0x100
FLAG_NAMES = {CERTIFIED: "certified", ACTIVE: "active", INFEASIBLE: "infeasible", INVALID: "invalid",
              NO_STOP: "no-stop", BLOCKED: "blocked", EVAL_CAP: "eval-cap", DONE: "done", SATURATED: "saturated"}
Z = F(0.0)


@dataclass(frozen=True)
class ShieldParams:
    """Mirror of ``polycc_shield_params_t``.  Defaults: the stock Crazyflie PID velocity loop at
    10 ms (polycc.sim.dynamics.CrazyflieParams) made conservative for the full quadrotor (tau, n_lat:
    docs/barrier.md section 8) and the app's shield defaults (polycc_controller.h)."""

    kappa: float = 100.0
    radius: float = 0.1
    h: float = 0.01
    k_v: float = 4.2803  # 25 deg/(m/s) * g, 1/s
    k_z: float = 9.3
    a_xy: float = 3.96  # g tan 22 deg
    a_up: float = 11.77  # 1.2 g
    a_dn: float = 5.69  # 0.58 g
    tau: float = 0.25  # conservative: the attitude loop's 1/6 s plus the rate loop and motor lag
    k1: float = 4.0
    k0: float = 4.0
    v_max: float = 3.0
    tube: float = 0.05
    v_term: float = 0.05
    a_term: float = 0.5
    a_brake: float = 3.0  # the brake's deceleration as modelled, m/s^2 (<= a_xy; it is commanded at a_xy)
    psi_cap: float = 0.0  # clearance cap D, m (0: off): psi <- min(psi, D), gradient 0 where capped
    n_lat: int = 3  # 20 ms estimator delay + the 10 ms until the decision is flown
    n_commit: int = 2  # two periods: a decision whose successor is up to a period late flies on its own certificate
    n_steps: int = 200
    max_evals: int = 10

    def f32(self) -> dict:
        return {f.name: (int(getattr(self, f.name)) if f.name.startswith(("n_", "max_")) else F(getattr(self, f.name)))
                for f in fields(self)}


@dataclass
class Job:
    """Mirror of ``polycc_shield_job_t`` after a run (the arrays up to index n)."""

    x: np.ndarray
    lam: np.ndarray
    u_c: np.ndarray
    u_d: np.ndarray
    a_end: np.ndarray
    psi: np.float32
    grad: np.ndarray
    c: np.float32
    min_c: np.float32
    n: int
    i: int
    cov: int
    evals: int
    flags: int


def _in(x, lo, hi) -> bool:
    return bool(x >= lo) and bool(x <= hi)


def _vec_ok(x, lim) -> bool:
    return all(_in(x[k], -lim, lim) for k in range(3))


def params_ok(q: dict) -> bool:
    return (_in(q["kappa"], B.KAPPA_MIN, B.KAPPA_MAX) and _in(q["radius"], Z, B.POS_MAX)
            and _in(q["h"], F("1.0e-4"), F(0.1)) and _in(q["k_v"], F("1.0e-3"), F(1e3))
            and _in(q["k_z"], F("1.0e-3"), F(1e3)) and _in(q["a_xy"], F("1.0e-3"), F(1e3))
            and _in(q["a_up"], F("1.0e-3"), F(1e3)) and _in(q["a_dn"], F("1.0e-3"), F(1e3))
            and _in(q["tau"], q["h"], F(10.0)) and _in(q["k1"], Z, F(1e3)) and _in(q["k0"], Z, F(1e4))
            and _in(q["v_max"], F("1.0e-3"), VA_MAX) and _in(q["tube"], Z, F(10.0))
            and _in(q["v_term"], Z, F(10.0)) and _in(q["a_term"], Z, F(100.0))
            and _in(q["a_brake"], F("1.0e-3"), q["a_xy"]) and _in(q["psi_cap"], Z, B.POS_MAX)
            and 1 <= q["n_steps"] <= MAX_STEPS and q["n_lat"] <= q["n_steps"]
            and q["n_commit"] <= q["n_steps"] - q["n_lat"] and 1 <= q["max_evals"] <= MAX_EVALS)


def _dot(a, b) -> np.float32:
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]



def _psi(scene: PackedScene, q: dict, p) -> tuple[np.float32, np.ndarray, bool]:
    kp = B.Params(kappa=float(q["kappa"]), radius=float(q["radius"]), beta=1.0, c_clf=0.0, v_max=1.0)
    psi, grad, flags = B.barrier(scene, kp, np.asarray(p, F).reshape(1, 3))
    psi, grad = psi[0], grad[0].copy()
    if q["psi_cap"] > Z and psi > q["psi_cap"]:
        psi, grad = q["psi_cap"], np.zeros(3, F)
    return psi, grad, bool(flags[0] & B.FLAG_INVALID)


def _cover(lam, n: int, i: int, c) -> int:
    j = i
    while j < n:
        L = (lam[j + 1] - lam[i]) + LEN_SLACK * lam[j + 1]
        if not (L <= c):
            break
        j += 1
    return j


def plan(scene: PackedScene, prm: ShieldParams, p, v, a0, u_app, u_d) -> Job:
    """Mirror of ``polycc_shield_plan``."""
    q = prm.f32()
    p, v, a0, u_app, u_d = (np.array(t, F).reshape(3) for t in (p, v, a0, u_app, u_d))
    job = Job(x=np.zeros((MAX_STEPS + 1, 3), F), lam=np.zeros(MAX_STEPS + 1, F), u_c=np.zeros(3, F),
              u_d=np.zeros(3, F), a_end=np.zeros(3, F), psi=Z, grad=np.zeros(3, F), c=Z, min_c=Z, n=0, i=0, cov=0,
              evals=0, flags=0)
    job.x[0] = p
    with np.errstate(all="ignore"):
        if not (params_ok(q) and _vec_ok(p, B.POS_MAX) and all(_vec_ok(t, VA_MAX) for t in (v, a0, u_app, u_d))):
            job.flags = INVALID | DONE
            return job
        psi, grad, bad = _psi(scene, q, p)
        job.evals = 1
        if bad:
            job.flags = INVALID | DONE
            return job
        job.psi, job.grad = psi, grad.copy()
        _candidate(job, q, v, u_d)
        _simulate(job, q, p, v, a0, u_app)
        job.c = job.psi - q["tube"]
        job.min_c = job.c
        if job.flags & DONE:
            return job
        if not (job.c >= Z):
            job.flags |= BLOCKED | DONE
            return job
        job.cov = _cover(job.lam, job.n, 0, job.c)
        if job.cov == job.n:
            job.flags |= CERTIFIED | DONE
    return job


def _candidate(job: Job, q: dict, v, u_d) -> None:
    g = job.grad
    ud = u_d.copy()
    if B.saturate(ud, q["v_max"]):
        job.flags |= SATURATED
    job.u_d = ud.copy()
    uc = ud.copy()
    g2 = _dot(g, g)
    gv = _dot(g, v)
    b = gv - (q["k1"] * gv + q["k0"] * job.psi) / q["k_v"]
    gu = _dot(g, ud)
    if gu < b:
        job.flags |= ACTIVE
        if not (g2 >= B.GRAD2_MIN):
            job.flags |= INFEASIBLE
            uc[:] = Z
        else:
            lam = (b - gu) / g2
            uc = np.array([ud[k] + lam * g[k] for k in range(3)], F)
            B.saturate(uc, q["v_max"])
            if _dot(g, uc) < b:
                job.flags |= INFEASIBLE
    job.u_c = uc


def brake(v, e) -> np.ndarray:
    """Mirror of ``polycc_shield_brake``: the backup's velocity command for the estimate v (m/s)."""
    v = np.asarray(v, F)
    e = F(e)
    u = np.zeros(3, F)
    n2 = v[0] * v[0] + v[1] * v[1]
    if n2 > e * e:
        s = e / np.sqrt(n2)
        u[0] = v[0] - s * v[0]
        u[1] = v[1] - s * v[1]
    return u


def _simulate(job: Job, q: dict, p, v0, a0, u_app) -> None:
    eb = q["a_brake"] / q["k_v"]
    g = q["h"] / q["tau"]
    h = q["h"]
    a2max = q["a_xy"] * q["a_xy"]
    adn = -q["a_dn"]
    n1, n2 = q["n_lat"], q["n_lat"] + q["n_commit"]
    v, a = v0.copy(), a0.copy()
    job.a_end = a0.copy()
    x, lam = job.x, job.lam
    x[0] = p
    lam[0] = Z
    for k in range(q["n_steps"]):
        u = u_app if k < n1 else (job.u_c if k < n2 else brake(v, eb))
        d = np.zeros(3, F)
        d[0] = q["k_v"] * (u[0] - v[0])
        d[1] = q["k_v"] * (u[1] - v[1])
        m2 = d[0] * d[0] + d[1] * d[1]
        if m2 > a2max:
            sc = q["a_xy"] / np.sqrt(m2)
            d[0] = d[0] * sc
            d[1] = d[1] * sc
        d[2] = q["k_z"] * (u[2] - v[2])
        if d[2] > q["a_up"]:
            d[2] = q["a_up"]
        if d[2] < adn:
            d[2] = adn
        a = a + g * (d - a)
        v = v + h * a
        s = h * v
        x[k + 1] = x[k] + s
        lam[k + 1] = lam[k] + np.sqrt(_dot(s, s))
        if k + 1 == n2:
            job.a_end = a.copy()
    job.n = q["n_steps"]
    if not (_dot(v, v) <= q["v_term"] * q["v_term"]) or not (_dot(a, a) <= q["a_term"] * q["a_term"]):
        job.flags |= NO_STOP | DONE


def simulate(prm: ShieldParams, p, v, a0, u_app, u_c) -> Job:
    """The closed-loop model alone (no psi, no validation): the path ``polycc_shield_simulate`` traces
    for the candidate ``u_c`` (for the benchmarks; ``job.x[: job.n + 1]``)."""
    q = prm.f32()
    p, v, a0, u_app, u_c = (np.array(t, F).reshape(3) for t in (p, v, a0, u_app, u_c))
    job = Job(x=np.zeros((MAX_STEPS + 1, 3), F), lam=np.zeros(MAX_STEPS + 1, F), u_c=u_c, u_d=u_c.copy(),
              a_end=np.zeros(3, F), psi=Z, grad=np.zeros(3, F), c=Z, min_c=Z, n=0, i=0, cov=0, evals=0, flags=0)
    with np.errstate(all="ignore"):
        _simulate(job, q, p, v, a0, u_app)
    return job


def advance(scene: PackedScene, prm: ShieldParams, job: Job) -> Job:
    """Mirror of ``polycc_shield_advance``."""
    q = prm.f32()
    if job.flags & DONE:
        return job
    if job.evals >= q["max_evals"]:
        job.flags |= EVAL_CAP | DONE
        return job
    with np.errstate(all="ignore"):
        j = job.cov if job.cov > job.i else job.i + 1
        psi, _, bad = _psi(scene, q, job.x[j])
        job.evals += 1
        if bad:
            job.flags |= BLOCKED | DONE
            return job
        cj = psi - q["tube"]
        if cj < job.min_c:
            job.min_c = cj
        L = (job.lam[j] - job.lam[job.i]) + LEN_SLACK * job.lam[j]
        if not (cj >= Z) or not (L <= job.c + cj):
            job.flags |= BLOCKED | DONE
            return job
        job.i, job.c = j, cj
        job.cov = _cover(job.lam, job.n, j, cj)
        if job.cov == job.n:
            job.flags |= CERTIFIED | DONE
    return job


def run(scene: PackedScene, prm: ShieldParams, p, v, a0, u_app, u_d) -> Job:
    """Mirror of ``polycc_shield_run``: plan, then advance until decided."""
    job = plan(scene, prm, p, v, a0, u_app, u_d)
    while not job.flags & DONE:
        advance(scene, prm, job)
    return job


def command(job: Job, prm: ShieldParams | None = None, v=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The velocity the gatekeeper flies now: the candidate if certified, else the backup, the brake
    policy (:func:`brake`, commanded at a_xy) at the velocity estimate ``v``."""
    prm = prm or ShieldParams()
    return job.u_c.copy() if job.flags & CERTIFIED else brake(v, F(prm.a_xy) / F(prm.k_v))


def flag_names(flags: int) -> list[str]:
    return [name for bit, name in FLAG_NAMES.items() if flags & bit]
