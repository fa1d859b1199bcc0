"""Benchmark: the shield (issue 18) against today's app, in the fast SITL (host build of the app).

Demo arena, the n = 150 cover (bench_sim's family), random start/goal pairs in free space; per
commanded speed (the app's vmax: 0.5, 1, 2, 3 m/s) and vehicle model (the Crazyflie-like model
and the full rigid-body quadrotor), the go-to-goal app flown

* ``app``: as shipped (braking term on, standard PID controller, no shield);
* ``shield``: braking term compiled out, the out-of-tree controller with polyccShield.enable = 1
  (the shield filters the app's setpoints; app radius 0.2 m so that the app's own first-order
  filter keeps clear of the shield's r + tube = 0.15 m).

``--modes`` adds the sources of those two on their own and the shield around today's app, so that
what the shield adds is measured against the same source:

* ``nobrake``: the ``shield`` row's source alone (braking term compiled out, app radius 0.2 m, no shield);
* ``app_r2``: today's app with radius 0.2 m (braking term on, no shield);
* ``app_shield``: that app with the shield on (braking term on, app radius 0.2 m, shield r = 0.1 m).

Columns: flights, goal reached, collisions (flights touching a ground-truth ellipsoid with the
0.1 m radius), minimum clearance (exact distance minus 0.1 m), realized minus commanded barrier
rate grad psi . (v - u) (Prop. 1 of seed 001; p1/p50/p99 over 100 Hz samples, m/s), jerk of the
true vehicle at 100 Hz (RMS, p99, m/s^3), mean time to goal (successful flights), shield
decisions with QP infeasibility and backup use per flight.  Wall-clock ratios are not the point
here; the shield's cost on board is its certified cycle budget (printed, from the header).

    python bench/bench_shield.py [--pairs N] [--jobs J] [--speeds 0.5,1,2,3] [--dynamics crazyflie,quadrotor]
        [--psi-caps 0,0.6]   (shield cells on min(psi, cap): a clearance-capped barrier, issue 18)
        [--gains 4:4,2:1]    (shield cells per ECBF gains k1:k0, polyccShield.k1/k0)

Real firmware (``--firmware FWDIR``, the CrazySim SITL tree or tarball): the modes of ``--modes`` (any of the
five above) on the first ``--fw-pairs`` pairs per speed, each flight a fresh SITL instance flown by real cflib
(:mod:`polycc.sim.firmware.flights`: HL takeoff to the start, app enabled, HL landing): ``app`` is the
shipped cf2 (PID controller), ``shield`` a cf2 with the braking term compiled out, the out-of-tree
controller (stabilizer.controller = 5 in the fork) and polyccShield.enable = 1 from the start height
(``app_shield``: the shipped cf2 with the same controller and shield, app radius 0.2 m). Model
"firmware" rows: collisions and clearance on the bridge's 100 Hz truth, jerk from its velocity, the
shield's logged counters; a second table pairs each mode's flights with the app's on the same pairs
(:func:`paired_jerk`); the rate gap from the app's logged command and estimate at 50 Hz, grad psi from the
host kernel (:meth:`polycc.sim.firmware.flights.FirmwareSimulator.rate_gap`). Next to them, model
"quadrotor" rows on the same pairs (fast sim) for the agreement.

    python bench/bench_shield.py --firmware ../shared/firmware/crazyflie-firmware-sitl-6a4d2d0.tar.xz \
        --fw-pairs 100 [--fw-minutes 90] [--speeds ...] [--modes app,shield,app_shield]

Each real-firmware flight is kept in the committed store bench/flights/ (bench/flight_store.py: per cf2
build, flight code and config, mode, speed and pair) and read instead of flown again, so the pairs per
speed accumulate over runs and machines; ``--fw-minutes`` stops flying after that much wall time.

Writes bench/results/shield.json (fast) and bench/results/shield_firmware.json (--firmware).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import CACHE, print_table, write_json  # noqa: E402

RUNS = CACHE / "shield_firmware_runs"  # runs of flights that did not land

RADIUS = 0.1
N_POLYS = 150


def fly_cell(job: dict) -> dict:
    from bench_sim import arena

    from polycc.sim.sitl import FlightConfig, Simulator

    t0 = time.perf_counter()
    mode = job["mode"]
    shield = mode in ("shield", "app_shield")
    sim = Simulator(job["header"], arena("demo"), brake=mode not in ("shield", "nobrake"))
    cfg = FlightConfig(vmax=job["speed"], radius=RADIUS if mode == "app" else 0.2, clearance_radius=RADIUS,
                       shield=shield,
                       shield_radius=RADIUS, shield_psi_cap=job["psi_cap"] if shield else 0.0,
                       shield_gains=job["gains"] if shield else None)
    trials = [sim.fly(s, g, job["dynamics"], cfg) for s, g in job["pairs"]]
    ok = [t for t in trials if t.success]
    gap = np.concatenate([t.rate_gap for t in trials if t.rate_gap is not None and len(t.rate_gap)] or [np.zeros(1)])
    jerk = np.concatenate([t.jerk for t in trials if t.jerk is not None and len(t.jerk)] or [np.zeros(1)])
    sh = [t.shield for t in trials if t.shield]
    per = (lambda k: float(np.mean([s[k] for s in sh]))) if sh else (lambda k: 0.0)
    return {
        **{k: v for k, v in job.items() if k not in ("pairs", "header")},
        "flights": len(trials), "goal": len(ok),
        "collisions": int(sum(t.collisions > 0 for t in trials)),
        "min_clearance_m": float(min(t.min_clearance_m for t in trials)),
        "gap_p1": float(np.percentile(gap, 1)), "gap_p50": float(np.percentile(gap, 50)),
        "gap_p99": float(np.percentile(gap, 99)),
        "jerk_rms": float(np.sqrt(np.mean(jerk ** 2))), "jerk_p99": float(np.percentile(jerk, 99)),
        "time_to_goal_s": float(np.mean([t.time_s for t in ok])) if ok else float("nan"),
        "decisions_per_flight": per("decisions"), "infeasible_per_flight": per("infeasible"),
        "backups_per_flight": per("backups"), "eval_caps_per_flight": per("eval_caps"),
        "outcomes": {o: sum(t.outcome == o for t in trials) for o in ("goal", "stuck", "timeout")},
        "wall_s": time.perf_counter() - t0,
    }


def _flight_record(t, start, goal) -> dict:
    """What the rows need of one firmware Trial, for the flight store (bench/flight_store.py)."""
    from flight_store import encode

    jerk = np.asarray(t.jerk if t.jerk is not None else np.zeros(0), np.float64)
    gap = np.asarray(t.rate_gap if t.rate_gap is not None else np.zeros(0), np.float64)
    return {"start": [float(v) for v in start], "goal": [float(v) for v in goal],
            "outcome": t.outcome, "success": bool(t.success), "time_s": float(t.time_s),
            "collisions": int(t.collisions), "min_clearance_m": float(t.min_clearance_m), "shield": t.shield,
            "landed": bool(t.extra.get("landed")), "sitl_reruns": int(t.extra.get("sitl_reruns", 0)),
            "rtf": float(t.extra.get("rtf") or 0.0), "wall_s": float(t.extra.get("wall_s") or 0.0),
            "jerk_rms": float(np.sqrt(np.mean(jerk ** 2))) if len(jerk) else float("nan"),
            "jerk": encode(jerk), "gap": encode(gap)}


def fly_firmware_cells(tree, header: Path, pairs, speeds, say=print, modes=("app", "shield"),
                       minutes: float | None = None, store: Path | None = None) -> list[dict]:
    """The real-firmware rows (module docstring) for ``modes`` (those of ``--modes``).

    Flights come from the committed flight store (bench/flight_store.py, bench/flights/) where they are
    there for this build, flight code, config and pair; the missing ones are flown one after the other
    (each SITL is lock-stepped at up to real time, and a second instance on a 2-core host starves the app
    task: 12-26x the late decisions and 1.16-1.30x the jerk, measured), pair by pair across all cells, so a
    run cut short by ``minutes`` (wall) leaves every cell with about the same pairs. Each flight is written
    to the store as it lands. A cell's row covers the pairs it holds of ``pairs``."""
    from bench_sim import arena
    from flight_store import STORE, Cell, store_key

    from polycc.sim.firmware.build import build_cf2
    from polycc.sim.firmware.flights import FirmwareSimulator
    from polycc.sim.sitl import FlightConfig, Simulator

    store = STORE if store is None else Path(store)
    ell = arena("demo")
    ref = Simulator(header)
    braked = {m: m not in ("shield", "nobrake") for m in modes}
    builds = {}
    if any(braked.values()):
        builds[True] = build_cf2(tree, header, log=say)
    if not all(braked.values()):
        builds[False] = build_cf2(tree, header, extra_cflags=["-DPOLYCC_APP_BRAKE_ACC=0.0f"], log=say)
    cfgs, cells = {}, {}
    for speed in speeds:
        for mode in modes:
            shield = mode in ("shield", "app_shield")
            cfg = FlightConfig(vmax=speed, radius=RADIUS if mode == "app" else 0.2, clearance_radius=RADIUS,
                               shield=shield, shield_radius=RADIUS)
            cfgs[speed, mode] = cfg
            cells[speed, mode] = Cell(store_key(builds[braked[mode]].key, cfg), mode, speed, store)
    todo = [(k, speed, mode) for k in range(len(pairs)) for speed in speeds for mode in modes
            if cells[speed, mode].get(k, *pairs[k]) is None]
    say(f"real firmware: {len(pairs) * len(cells) - len(todo)} flights in the store ({store}), {len(todo)} to fly"
        + (f", for at most {minutes:g} min" if minutes is not None else ""))
    t_run = time.perf_counter()
    sims, flown = {}, {}
    for i, (k, speed, mode) in enumerate(todo):
        if minutes is not None and time.perf_counter() - t_run > 60.0 * minutes:
            say(f"--fw-minutes {minutes:g} used up: {len(todo) - i} flights left for a later run")
            break
        s0, g = pairs[k]
        b = braked[mode]
        if b not in sims:
            sims[b] = FirmwareSimulator(header, tree, ref.packed, ref.kappa, ell, build=builds[b])
        # each flight's cf2.log, bridge.err and 100 Hz truth are kept only if it did not land (one in ~165 did
        # not, and replays of it landed: the next one can be examined)
        runs = RUNS / f"{mode}_{speed:g}ms_pair{k}"
        shutil.rmtree(runs, ignore_errors=True)
        sims[b].run_root = runs
        t = sims[b].fly(s0, g, cfgs[speed, mode])
        if t.extra.get("landed", True):
            shutil.rmtree(runs, ignore_errors=True)
        else:
            say(f"firmware {mode} {speed:g} m/s pair {k + 1} did not land within the wait: its run is kept in {runs}")
        cells[speed, mode].put(k, _flight_record(t, s0, g))
        flown[speed, mode] = flown.get((speed, mode), 0) + 1
        say(f"firmware {mode} {speed:g} m/s pair {k + 1}/{len(pairs)} ({i + 1}/{len(todo)}): {t.outcome}, "
            f"clearance {t.min_clearance_m:+.3f} m, {t.time_s:.1f} s")
    rows = []
    for speed in speeds:
        for mode in modes:
            cell = cells[speed, mode]
            got = [(k, cell.get(k, *pairs[k])) for k in range(len(pairs))]
            rows.append(_firmware_row(speed, mode, [(k, r) for k, r in got if r is not None], cell,
                                      builds[braked[mode]].key, flown.get((speed, mode), 0)))
    return rows


def _firmware_row(speed: float, mode: str, recs: list[tuple[int, dict]], cell, cf2_key: str, flown: int) -> dict:
    """One firmware row from a cell's records (pair number, record)."""
    from flight_store import decode

    nan = float("nan")
    jerks = [decode(r["jerk"]) for _, r in recs]
    gaps = [decode(r["gap"]) for _, r in recs]
    jerk = np.concatenate([j for j in jerks if len(j)] or [np.zeros(1)])
    gap = np.concatenate([x for x in gaps if len(x)] or [np.full(1, nan)])
    ok = [r for _, r in recs if r["success"]]
    sh = [r["shield"] for _, r in recs if r["shield"]]
    per = (lambda k: float(np.mean([x.get(k, 0) for x in sh]))) if sh else (lambda k: 0.0)

    def pct(a, q):
        return float(np.percentile(a, q)) if np.isfinite(a).all() else None

    return {
        "dynamics": "firmware", "speed": float(speed), "mode": mode, "psi_cap": 0.0, "gains": None,
        "flights": len(recs), "goal": len(ok), "collisions": int(sum(r["collisions"] > 0 for _, r in recs)),
        "min_clearance_m": float(min((r["min_clearance_m"] for _, r in recs), default=nan)),
        "gap_p1": pct(gap, 1), "gap_p50": pct(gap, 50), "gap_p99": pct(gap, 99),
        "jerk_rms": float(np.sqrt(np.mean(jerk ** 2))), "jerk_p99": float(np.percentile(jerk, 99)),
        # per flight, pair by pair (paired_jerk compares the modes on the same pairs)
        "pair_ids": [k for k, _ in recs], "flight_jerk_rms": [r["jerk_rms"] for _, r in recs],
        "flight_jerk_rms_flown": [_rms(j[HANDOVER_SAMPLES:]) for j in jerks],
        "flight_outcome": [r["outcome"] for _, r in recs],
        "time_to_goal_s": float(np.mean([r["time_s"] for r in ok])) if ok else nan,
        "decisions_per_flight": per("decisions"), "infeasible_per_flight": per("infeasible"),
        "backups_per_flight": per("backups"), "eval_caps_per_flight": None,
        # ticks a late decision was flown on to its certified successor / braked for want of one
        "bridged_per_flight": per("bridged"), "expired_per_flight": per("expired"),
        "outcomes": {o: sum(r["outcome"] == o for _, r in recs) for o in ("goal", "stuck", "timeout")},
        "landed": sum(r["landed"] for _, r in recs),
        "sitl_reruns": sum(r["sitl_reruns"] for _, r in recs),
        "rtf_mean": float(np.mean([r["rtf"] for _, r in recs])) if recs else nan,
        "flown_now": flown, "build_key": cf2_key[:16], "store": cell.path.name,
        "wall_s": float(sum(r.get("wall_s", 0.0) for _, r in recs)),
    }


OUTCOME_CLASSES = {  # the two flights of a pair by whether each reached its goal (mode, base)
    "all": lambda m, b: True,
    "both reach the goal": lambda m, b: m and b,
    "only the base reaches it": lambda m, b: b and not m,
    "only the mode reaches it": lambda m, b: m and not b,
    "neither": lambda m, b: not (m or b),
}


HANDOVER_SAMPLES = 3  # the first 30 ms of a flight's 100 Hz jerk: the hand-over from the high-level commander


def _rms(a) -> float:
    a = np.asarray(a, np.float64)
    return float(np.sqrt(np.mean(a ** 2))) if len(a) else float("nan")


def paired_jerk(rows: list[dict], base: str = "app", by_outcome: bool = False,
                key: str = "flight_jerk_rms") -> list[dict]:
    """Per speed and mode, the jerk RMS of each flight against ``base``'s flight of the same pair (firmware
    rows): median and geometric mean of the ratios, the pairs where the mode's flight is smoother, and the
    Wilcoxon signed-rank p-value (two-sided, on the log ratios). The pooled RMS of a cell is dominated by a
    few flights (a 25-pair cell's pooled figure moved by several m/s^3 between runs); the pairing removes the
    pair-to-pair spread of the paths, which both modes share. ``by_outcome``: one row per class of
    :data:`OUTCOME_CLASSES` as well (on 398 flights the 0.5 m/s excess was all in pairs where the shield's
    source stalled: docs/barrier.md section 8). ``key``: the per-flight figure compared, ``flight_jerk_rms`` (the
    whole flight) or ``flight_jerk_rms_flown`` (after the first 30 ms: the hand-over from the high-level commander,
    the largest jerk of most flights in both modes, which hides what the flight in between does)."""
    from scipy.stats import wilcoxon

    out = []
    fw = [r for r in rows if r["dynamics"] == "firmware" and r.get(key)]
    for r in fw:
        b = next((x for x in fw if x["speed"] == r["speed"] and x["mode"] == base), None)
        if r["mode"] == base or b is None:
            continue
        bj, rj = dict(zip(b["pair_ids"], b[key])), dict(zip(r["pair_ids"], r[key]))
        bo = dict(zip(b["pair_ids"], b.get("flight_outcome") or [None] * len(b["pair_ids"])))
        ro = dict(zip(r["pair_ids"], r.get("flight_outcome") or [None] * len(r["pair_ids"])))
        common = sorted(set(bj) & set(rj))
        for name, test in OUTCOME_CLASSES.items() if by_outcome else [("all", OUTCOME_CLASSES["all"])]:
            if name != "all" and any(bo[k] is None or ro[k] is None for k in common):
                continue
            ks = [k for k in common if test(ro[k] == "goal", bo[k] == "goal")]
            a, o = np.asarray([bj[k] for k in ks], float), np.asarray([rj[k] for k in ks], float)
            ok = np.isfinite(a) & np.isfinite(o) & (a > 0) & (o > 0)
            lr = np.log(o[ok] / a[ok])
            p = float(wilcoxon(lr).pvalue) if len(lr) >= 6 and np.any(lr != 0) else float("nan")
            out.append({"speed": r["speed"], "mode": r["mode"], "base": base, "figure": key, "outcomes": name,
                        "pairs": int(ok.sum()),
                        "median_ratio": float(np.exp(np.median(lr))) if len(lr) else float("nan"),
                        "geomean_ratio": float(np.exp(np.mean(lr))) if len(lr) else float("nan"),
                        "smoother": int((lr < 0).sum()), "wilcoxon_p": p})
    return out


def _table_rows(rows):
    f = lambda v: "-" if v is None else v  # noqa: E731
    return [[r["dynamics"], r["speed"], r["mode"], r["psi_cap"],
             "-" if r["gains"] is None else "{:g}:{:g}".format(*r["gains"]), f"{r['goal']}/{r['flights']}",
             r["collisions"], r["min_clearance_m"], f(r["gap_p1"]), f(r["gap_p50"]), f(r["gap_p99"]), r["jerk_rms"],
             r["jerk_p99"], r["time_to_goal_s"], r["infeasible_per_flight"], r["backups_per_flight"],
             r["decisions_per_flight"]] for r in rows]


HEAD = ["model", "v m/s", "mode", "cap m", "k1:k0", "goal", "coll.", "min clr m", "gap p1", "gap p50", "gap p99",
        "jerk rms", "jerk p99", "t goal s", "infeas./fl", "backup/fl", "dec./fl"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=100, help="random start/goal pairs per speed (default 100)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--speeds", default="0.5,1,2,3", help="commanded speeds, m/s")
    ap.add_argument("--dynamics", default="crazyflie,quadrotor", help="vehicle models")
    ap.add_argument("--min-distance", type=float, default=1.5, help="minimum start-goal distance, m")
    ap.add_argument("--psi-caps", default="0", help="shield cells per psi cap, m (0: off; e.g. 0,0.6)")
    ap.add_argument("--gains", default="4:4", help="shield cells per ECBF gains k1:k0 (1/s : 1/s^2; default 4:4, "
                                                   "the app's; e.g. 4:4,2:1)")
    ap.add_argument("--modes", default="app,shield", help="comma list of app, shield, nobrake, app_r2, app_shield "
                                                          "(module docstring)")
    ap.add_argument("--firmware", metavar="FWDIR", help="also fly the real firmware (CrazySim SITL tree or tarball)")
    ap.add_argument("--fw-pairs", type=int, default=5, help="with --firmware: pairs per speed and mode (default 5); "
                    "flights already in the store (bench/flights/shield_firmware) are read, not flown")
    ap.add_argument("--fw-minutes", type=float, default=None, help="with --firmware: stop flying new flights after "
                    "this many minutes of wall time (the store keeps them; default: no limit)")
    args = ap.parse_args()
    from bench_sim import pairs_for, write_header

    from polycc.sim.app_ffi import AppSim

    header = write_header("demo", N_POLYS)
    pairs = pairs_for(header, "demo", args.pairs, args.min_distance, seed=18)
    app = AppSim(header)
    lib = app.lib
    budget = {"scene_worst_cycles": int(lib.polycc_app_scene_worst_cycles()),
              "plan_max_evals": int(lib.polycc_controller_max_evals()),
              "plan_worst_cycles": int(lib.polycc_controller_plan_worst_cycles()),
              "period_share_cycles": 168_000 * 10 * int(lib.POLYCC_SHIELD_CPU_SHARE_PERCENT) // 100}
    print(f"shield plan budget: {budget}")
    modes = args.modes.split(",")
    unknown = set(modes) - {"app", "shield", "nobrake", "app_r2", "app_shield"}
    if unknown:
        ap.error(f"--modes: unknown {sorted(unknown)}")
    if args.firmware:
        return firmware_main(args, header, pairs, budget)
    caps = [float(c) for c in args.psi_caps.split(",")]
    gains = [tuple(float(x) for x in g.split(":")) for g in args.gains.split(",")]
    jobs = [{"header": str(header), "pairs": pairs, "speed": float(s), "dynamics": d, "mode": m, "psi_cap": c,
             "gains": k}
            for d in args.dynamics.split(",") for s in args.speeds.split(",")
            for m, c, k in [(m, 0.0, None) for m in modes if m not in ("shield", "app_shield")]
            + [(m, c, k) for m in modes if m in ("shield", "app_shield") for c in caps for k in gains]]
    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        futs = {ex.submit(fly_cell, j): i for i, j in enumerate(jobs)}
        for f in as_completed(futs):  # partial results are kept as cells finish
            rows.append((futs[f], f.result()))
            write_json("shield", {"pairs": args.pairs, "budget": budget, "partial": len(rows) < len(jobs),
                                  "rows": [r for _, r in sorted(rows, key=lambda t: t[0])],
                                  "wall_s": time.perf_counter() - t0})
            print(f"cell {len(rows)}/{len(jobs)} done", flush=True)
    rows = [r for _, r in sorted(rows, key=lambda t: t[0])]
    print_table(f"Shield vs today's app, demo arena n={N_POLYS}, {args.pairs} pairs per speed (fast SITL)", HEAD,
                _table_rows(rows))
    write_json("shield", {"pairs": args.pairs, "budget": budget, "rows": rows, "wall_s": time.perf_counter() - t0})
    return 0


def firmware_main(args, header: Path, pairs, budget) -> int:
    """--firmware: the real-firmware rows and, on the same pairs, the fast quadrotor rows, for ``--modes``
    (default app,shield): the firmware flights alone (stored or flown), then the fast cells (``--jobs``
    processes) on the pairs the firmware cells hold."""
    t0 = time.perf_counter()
    speeds = [float(v) for v in args.speeds.split(",")]
    modes = args.modes.split(",")
    sub = pairs[: args.fw_pairs]
    fw_rows = fly_firmware_cells(args.firmware, header, sub, speeds, modes=modes, minutes=args.fw_minutes)
    held = [sub[k] for k in sorted({k for r in fw_rows for k in r["pair_ids"]})]
    jobs = [{"header": str(header), "pairs": held, "speed": speed, "dynamics": "quadrotor", "mode": mode,
             "psi_cap": 0.0, "gains": None} for speed in speeds for mode in modes]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:  # the fast sim on the same pairs
        rows = list(ex.map(fly_cell, jobs)) if held else []
    out = sorted(rows + fw_rows, key=lambda r: (r["speed"], r["mode"], r["dynamics"]))
    print_table(f"Shield vs today's app on the REAL firmware (SITL) and the fast quadrotor, demo arena n={N_POLYS}, "
                f"{len(held)} of {len(sub)} pairs per speed", HEAD, _table_rows(out))
    paired = paired_jerk(fw_rows, by_outcome=True)
    flown = paired_jerk(fw_rows, key="flight_jerk_rms_flown")
    for title, rows_ in (("Jerk RMS per flight against today's app on the same pair (real firmware), all pairs and by "
                          "which of the two flights reached its goal", paired),
                         ("The same after the first 30 ms of each flight (the hand-over from the high-level "
                          "commander)", flown)):
        if rows_:
            print_table(title, ["v m/s", "mode", "pairs (outcomes)", "pairs", "median ratio", "geo. mean ratio",
                                "smoother", "Wilcoxon p"],
                        [[r["speed"], r["mode"], r["outcomes"], r["pairs"], r["median_ratio"], r["geomean_ratio"],
                          f"{r['smoother']}/{r['pairs']}", r["wilcoxon_p"]] for r in rows_])
    paired += flown
    write_json("shield_firmware", {"pairs": len(sub), "pairs_held": len(held), "budget": budget, "rows": out,
                                   "paired": paired, "partial": False, "wall_s": time.perf_counter() - t0})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
