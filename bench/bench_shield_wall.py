"""Benchmark: does the realized path stay within the tube of the shield's modelled path? (issue 18)

Two measurements of assumption (i) of docs/barrier.md section 8 (the real closed loop stays within
e_tube of the modelled *path*), both against the Crazyflie-like and the full rigid-body quadrotor
models (polycc.sim.dynamics), in metres:

* ``open-loop``: the vehicle flies a velocity command (0.5-3 m/s, 0/29/45 degrees from the body x
  axis) for 0.3 s, 0.6 s (mid-acceleration) or 4 s (cruise), then the shield's backup (its brake
  policy, commanded at a_xy from the 20 ms-old velocity estimate every 1 ms) after the latency;
  the shield's own model (polycc.onboard.shield, float32 mirror of the C) predicts the path from
  the estimate.  Excess = the largest distance of a realized point from the modelled polyline.
* ``wall``: a client's world-frame velocity stream at the wall x in [2, 2.3] (y in [-2, 2], z in
  [0, 2]) for 5 s through the app's shield (fast SITL, the C through the host shims), at 0, 30 and
  60 degrees from the wall normal, psi capped (polyccShield.psicap) or not; minimum clearance
  (distance to the box minus r = 0.1 m; the model promises e_tube = 0.05) and the excess of the
  realized path, from each certified plan until the next one, beyond that plan's path.

    python bench/bench_shield_wall.py [--speeds 0.5,1,2,3] [--angles 0,30,60] [--caps 0,0.6] [--seconds 5]

Writes bench/results/shield_wall.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import print_table, write_json  # noqa: E402

R = 0.1
LO, HI = np.array([2.0, -2.0, 0.0]), np.array([2.3, 2.0, 2.0])
MODELS = ("crazyflie", "quadrotor")


def path_excess(points: np.ndarray, path: np.ndarray) -> float:
    """Largest distance of ``points`` (N x 3) from the polyline ``path`` (M x 3), m."""
    a, b = path[:-1], path[1:]
    d = b - a
    l2 = (d * d).sum(1) + 1e-18
    worst = 0.0
    for p in points:
        t = np.clip(((p - a) * d).sum(1) / l2, 0.0, 1.0)
        worst = max(worst, float(np.sqrt((((a + t[:, None] * d) - p) ** 2).sum(1)).min()))
    return worst


def box_clearance(q: np.ndarray) -> float:
    if np.all((q >= LO) & (q <= HI)):
        return -float(np.min(np.minimum(q - LO, HI - q))) - R
    return float(np.linalg.norm(np.maximum(np.maximum(LO - q, q - HI), 0.0))) - R


def open_loop(dyn: str, speed: float, prm) -> float:
    from polycc.onboard import shield as S
    from polycc.sim.dynamics import make_dynamics

    q = prm.f32()
    e_cmd = np.float32(q["a_xy"] / q["k_v"])
    worst = 0.0
    for t_acc in (0.3, 0.6, 4.0):
        for ang in (0.0, 0.5, np.pi / 4):
            m = make_dynamics(dyn)
            m.reset(np.array([0.0, 0.0, 1.0]))
            u = speed * np.array([np.cos(ang), np.sin(ang), 0.0])
            for _ in range(int(round(t_acc / 0.01))):
                m.step(u, 0.01)
            pe, ve = m.estimate()
            job = S.simulate(prm, pe, ve, m.a, u, np.zeros(3))
            real = [m.p.copy()]
            for k in range(2500):  # 1 ms ticks: the latency under u, then the backup from the estimate
                m.step(u if k < 10 * prm.n_lat else S.brake(m.estimate()[1], e_cmd).astype(np.float64), 0.001)
                if k % 10 == 9:
                    real.append(m.p.copy())
            worst = max(worst, path_excess(np.array(real), job.x[: job.n + 1].astype(np.float64)))
    return worst


def wall_flight(header: Path, dyn: str, speed: float, cap: float, ang_deg: float, seconds: float) -> dict:
    from polycc.sim.sitl_device import SitlDeviceModel

    m = SitlDeviceModel(header, start=(0.0, 0.0, 1.0), dynamics=dyn)
    lib = m.app.lib
    m.app.set_param("stabilizer", "controller", int(lib.ControllerTypeOot))
    m.app.set_param("polyccShield", "enable", 1)
    m.app.set_param("polyccShield", "radius", R)
    m.app.set_param("polyccShield", "psicap", cap)
    a = np.radians(ang_deg)
    v = (speed * np.cos(a), speed * np.sin(a), 0.0)
    plans, true, last, worst = [], [], 0, np.inf
    while m.sim_ms < seconds * 1000:
        if m.sim_ms % 10 == 0:
            m._set_client(True, mode=(2, 2, 2), v=v)
        m.step()
        true.append(m.dyn.p.copy())
        worst = min(worst, box_clearance(m.dyn.p))
        tr = lib.polycc_controller_trace()
        if tr.decisions != last:
            last = tr.decisions
            j = lib.polycc_controller_job()
            if j.flags & 0x01 and j.n:  # certified: keep its modelled path
                plans.append((m.sim_ms, np.array([[j.x[k][i] for i in range(3)] for k in range(j.n + 1)])))
    true = np.array(true)
    excess = 0.0
    for (t, path), nxt in zip(plans, plans[1:] + [(len(true), None)]):
        seg = true[max(0, t - 1): nxt[0]]
        if len(seg):
            excess = max(excess, path_excess(seg[::2], path))
    tr = lib.polycc_controller_trace()
    return {"model": dyn, "speed": speed, "cap": cap, "angle_deg": ang_deg, "min_clearance_m": float(worst),
            "excess_m": excess, "backups": int(tr.backups), "decisions": int(tr.decisions)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speeds", default="0.5,1,2,3", help="commanded speeds, m/s")
    ap.add_argument("--angles", default="0,30,60", help="stream angles from the wall normal, degrees")
    ap.add_argument("--caps", default="0,0.6", help="psi caps, m (0: off)")
    ap.add_argument("--seconds", type=float, default=5.0, help="stream duration, s")
    args = ap.parse_args()
    from polycc.codegen.header import write_outputs
    from polycc.geometry.halfplanes import axis_box
    from polycc.onboard.shield import ShieldParams

    speeds = [float(s) for s in args.speeds.split(",")]
    t0 = time.perf_counter()
    prm = ShieldParams()
    ol = [{"model": d, "speed": s, "excess_m": open_loop(d, s, prm)} for d in MODELS for s in speeds]
    print_table(f"Open-loop braking: realized path beyond the shield's modelled path, m (tube {prm.tube})",
                ["model"] + [f"{s:g} m/s" for s in speeds],
                [[d] + [r["excess_m"] for r in ol if r["model"] == d] for d in MODELS])
    d = Path(tempfile.mkdtemp(prefix="polycc-wall-"))
    write_outputs(d, [axis_box(list(LO), list(HI))], {"kappa": 100.0})
    rows = [wall_flight(d / "polytopes.h", dyn, s, float(c), float(a), args.seconds)
            for dyn in MODELS for c in args.caps.split(",") for a in args.angles.split(",") for s in speeds]
    print_table("Velocity stream at a wall through the shield: min clearance / excess beyond the certified path, m",
                ["model", "cap m", "angle"] + [f"{s:g} m/s" for s in speeds],
                [[dyn, c, a] + [f"{r['min_clearance_m']:+.3f} / {r['excess_m']:.3f}" for r in rows
                                if (r["model"], r["cap"], r["angle_deg"]) == (dyn, c, a)]
                 for dyn in MODELS for c in sorted({r["cap"] for r in rows})
                 for a in sorted({r["angle_deg"] for r in rows})])
    write_json("shield_wall", {"open_loop": ol, "wall": rows, "tube_m": prm.tube, "wall_s": time.perf_counter() - t0})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
