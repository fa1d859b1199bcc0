"""Cortex-M4 cost model of one barrier evaluation (``polycc_step``), for budgets and summaries.

    cycles = FIXED + PER_CLUSTER * clusters + PER_ENTERED * polytopes entered
             + PER_POLY * polytopes evaluated + PER_PLANE * their half-planes

Coefficients are fitted to the upper end of the cycle range of the worst-case rows of
``bench/bench_kernel.py`` for scene format 3 (quantized records, shared normal table), which
runs the ARM build of ``polycc_kernel.c`` instruction by instruction (unicorn + capstone,
documented Cortex-M4 cycle model), and rounded so that the model is at or above every row
(0-10 % above): e.g. 150 polytopes / 1999 half-planes measured 176.7k cycles (1051.6 us),
model 180.9k; 150 / 3720: 297.6k (1771.6 us), model 301.4k; 150 / 9734 (64 KiB filled):
707.6k (4212 us), model 722.3k.  Format 3 costs about 70 cycles per evaluated half-plane
(index load, table address, int->float of the offset) against ~28 in format 2.

* worst case: every polytope entered and evaluated;
* typical: the float32 reference (:func:`polycc.onboard.barrier.barrier` with ``stats``) counts the
  polytopes the kernel enters and evaluates at positions sampled in the free space of the
  scene's bounding box, so the culling is the kernel's own.
"""

from __future__ import annotations

import numpy as np

from polycc.onboard.layout import PackedScene, n_clusters_for

CPU_HZ = 168e6
DEFAULT_CPU_SHARE = 0.2
DEFAULT_RATE_HZ = 500.0  # with DEFAULT_CPU_SHARE: a certified worst case of 400 us (67 200 cycles)
FIXED_CYCLES = 2500.0
PER_CLUSTER_CYCLES = 60.0
PER_ENTERED_CYCLES = 60.0
PER_POLY_CYCLES = 190.0
PER_PLANE_CYCLES = 70.0
INDEX_LOOKUP_CYCLES = 80.0  # cell lookup of the spatial index (float32 cell, two list loads)
INDEX_LEVEL_CYCLES = 30.0  # one octree level of the lookup
PER_EXP_PLANE_CYCLES = 135.0  # extra for a half-plane on the soft-max's exp path (new maximum or accumulated)


def cycles(n_clusters: float, entered: float, evaluated: float, planes: float) -> float:
    return (FIXED_CYCLES + PER_CLUSTER_CYCLES * n_clusters + PER_ENTERED_CYCLES * entered
            + PER_POLY_CYCLES * evaluated + PER_PLANE_CYCLES * planes)


def cycle_budget(rate_hz: float, cpu_share: float = DEFAULT_CPU_SHARE) -> float:
    """Cycles available per evaluation: ``cpu_share`` of the 168 MHz CPU at ``rate_hz``."""
    return cpu_share * CPU_HZ / rate_hz


def plane_budget(avail_cycles: float, n_polys: int) -> int:
    """Half-planes whose worst-case evaluation with ``n_polys`` polytopes (all entered and
    evaluated) fits in ``avail_cycles``."""
    avail = avail_cycles - cycles(n_clusters_for(n_polys), n_polys, n_polys, 0)
    return max(0, int(avail // PER_PLANE_CYCLES))


def us(cyc) -> np.ndarray:
    """Cycles -> microseconds at 168 MHz, rounded up (what ``usecTimestamp`` would show)."""
    return np.ceil(np.asarray(cyc, np.float64) / CPU_HZ * 1e6).astype(np.int64)


def indexed_cycles(polys, planes, depth=0, exp_planes=None):
    """Cycles of one evaluation through the spatial index when the leaf (``depth`` octree levels below
    its cell) lists ``polys`` polytopes with ``planes`` half-planes in all, every one of them entered,
    evaluated and fully scanned, ``exp_planes`` of the planes on the exp path (None: all of them)."""
    exp_planes = planes if exp_planes is None else exp_planes
    return (cycles(0, polys, polys, planes) + INDEX_LOOKUP_CYCLES + INDEX_LEVEL_CYCLES * np.asarray(depth, np.float64)
            + PER_EXP_PLANE_CYCLES * np.asarray(exp_planes, np.float64))


def _leaf_cost(polys, planes, depth, exp_planes):
    return float(indexed_cycles(polys, planes, depth, exp_planes))


def leaf_cycles(packed: PackedScene, kappa: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """(list ids, certified cycles) of every non-empty leaf box of the index: every listed polytope and
    plane evaluated, the planes that can take the exp path there at ``kappa`` (the build kappa; the
    figure holds for any kappa at or above it) charged for it, the octree descent to its depth."""
    from polycc.onboard.index import leaf_work

    w = leaf_work(packed, kappa)
    return w[:, 0], indexed_cycles(w[:, 2], w[:, 3], w[:, 1], w[:, 4])


def worst_cycles(packed: PackedScene, kappa: float = 100.0) -> float:
    """Certified worst case of one evaluation.  With a spatial index: the maximum over the cells (each
    list's polytopes and half-planes all evaluated) and the outside-B path (no polytope).  Without:
    every cluster, polytope and half-plane evaluated."""
    if packed.index is not None:
        _, cyc = leaf_cycles(packed, kappa)
        return float(max(np.max(cyc, initial=0.0), indexed_cycles(0, 0)))
    return cycles(packed.n_clusters, packed.n_polys, packed.n_polys, packed.n_planes)


def state_cycles(packed: PackedScene, params, X: np.ndarray) -> np.ndarray:
    """Modelled cycles at each state of X (n, 3), metres: the polytopes the kernel enters and
    evaluates there, counted by the float32 reference (its culling is the kernel's own)."""
    from polycc.onboard.barrier import barrier

    X = np.asarray(X, np.float32).reshape(-1, 3)
    if len(X) == 0:
        return np.zeros(0)
    stats: dict = {}
    barrier(packed, params, X, stats=stats)
    ev = np.asarray(stats["evaluated"], np.float64)
    mean_planes = packed.n_planes / max(packed.n_polys, 1)
    if packed.index is not None:
        _, depth = packed.index_leaf(X)
        # FIXED once (in indexed_cycles), plus the work counted by the reference
        work = cycles(0, np.asarray(stats["entered"], np.float64), ev, ev * mean_planes) - FIXED_CYCLES
        return indexed_cycles(0, 0, depth) + work
    return cycles(packed.n_clusters, np.asarray(stats["entered"], np.float64), ev, ev * mean_planes)


def estimate_us(packed: PackedScene, kappa: float = 100.0, samples: int = 400, seed: int = 0) -> dict:
    """Modelled microseconds per evaluation at 168 MHz: typical (median over free positions
    sampled in the polytopes' bounding box) and worst case."""
    from polycc.onboard.barrier import Params, barrier

    P = packed.polys
    c = np.stack([P["cx"], P["cy"], P["cz"]], axis=1).astype(np.float64)
    r = P["r_out"].astype(np.float64)
    lo, hi = (c - r[:, None]).min(0), (c + r[:, None]).max(0)
    x = np.random.default_rng(seed).uniform(lo, hi, (samples * 4, 3)).astype(np.float32)
    params = Params(kappa=kappa, radius=0.0)
    psi, _, _ = barrier(packed, params, x)
    free = psi > 0
    if not free.any():
        free[:] = True
    typ = state_cycles(packed, params, x[free])
    return {"typical_us": float(np.median(typ) / CPU_HZ * 1e6),
            "worst_us": float(worst_cycles(packed, kappa) / CPU_HZ * 1e6),
            "worst_is_certified": packed.index is not None}


# The shield's plan (firmware_app/src/polycc_controller.[ch], docs/barrier.md section 8): one
# polycc_shield_run per 10 ms period in the app task, as many psi evaluations as fit its CPU share.
# SHIELD_STEP_CYCLES: polycc_shield_simulate over 200 saturated steps ran 41 980-47 223 cycles in
# bench/bench_kernel.py's Cortex-M4 model (unicorn + timing table), plus the coverage walk
# (~20 cycles per step): 236 per step; the brake policy (issue 18) adds one sqrt and one divide per
# braking step (~2 x 14 cycles, estimated, not re-measured): 300.
SHIELD_PERIOD_TICKS = 10
SHIELD_CPU_SHARE_PERCENT = 25
SHIELD_FIXED_CYCLES = 4000
SHIELD_STEP_CYCLES = 300
SHIELD_MAX_STEPS = 200
SHIELD_MAX_EVALS = 32


def shield_max_evals(scene_worst_cycles: int) -> int:
    """psi evaluations per plan (``polycc_controller_max_evals``); 0: the shield is refused."""
    avail = int(CPU_HZ) // 1000 * SHIELD_PERIOD_TICKS * SHIELD_CPU_SHARE_PERCENT // 100
    own = SHIELD_FIXED_CYCLES + SHIELD_STEP_CYCLES * SHIELD_MAX_STEPS
    if avail <= own or scene_worst_cycles <= 0:
        return 0
    return min(SHIELD_MAX_EVALS, (avail - own) // int(scene_worst_cycles))


def shield_plan_cycles(scene_worst_cycles: int) -> int:
    """Certified worst case of one plan, cycles (``polycc_controller_plan_worst_cycles``)."""
    return (SHIELD_FIXED_CYCLES + SHIELD_STEP_CYCLES * SHIELD_MAX_STEPS
            + shield_max_evals(scene_worst_cycles) * int(scene_worst_cycles))
