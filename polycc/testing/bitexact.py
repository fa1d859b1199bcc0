"""Shared pieces of the bit-exactness tests: scenes, adversarial states, the uint32 comparison, and
the ARM toolchain check (``POLYCC_REQUIRE_ARM=1`` turns a missing toolchain into a failure)."""

from __future__ import annotations

import os
from functools import lru_cache

import numpy as np

from polycc.geometry.halfplanes import axis_box
from polycc.onboard import barrier as B
from polycc.onboard.layout import pack_scene
from polycc.testing.synthetic import pad_to_planes, random_hull_polytopes

FIELDS = ("psi", "grad", "u_nom", "u")
PARAMS = [B.Params(), B.Params(kappa=30.0, radius=0.1, beta=2.0, c_clf=0.5, v_max=0.5),
          B.Params(kappa=1000.0, radius=0.0, beta=0.5, c_clf=3.0, v_max=2.0)]


_SEEDS = {"hulls": 1, "boxes": 2, "planes4096": 3}
SCENES = list(_SEEDS)


@lru_cache(maxsize=None)
def scene(name: str):
    rng = np.random.default_rng(_SEEDS[name])
    if name == "hulls":
        return pack_scene(random_hull_polytopes(rng, 30))
    if name == "boxes":
        boxes = []
        for _ in range(40):
            lo = np.round(rng.uniform(0, 9, 3) * 8) / 8  # exact binary coordinates: faces hit exactly
            boxes.append(axis_box(lo, lo + np.round(rng.uniform(0.125, 1.0, 3) * 8) / 8))
        return pack_scene(boxes)
    if name == "planes4096":
        return pack_scene(pad_to_planes(random_hull_polytopes(rng, 150, points=(12, 16)), 4096), merge_duplicates=False)
    raise KeyError(name)


def states(sc, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random states: the room, points near faces/vertices of the polytopes, and far points."""
    rng = np.random.default_rng(seed)
    m = sc.plane_matrix().astype(np.float64)
    n_room, n_near = n // 2, n // 2 - n // 20
    room = rng.uniform(-1.0, 11.0, (n_room, 3)) * np.array([1, 1, 0.4])
    cs = np.c_[sc.polys["cx"], sc.polys["cy"], sc.polys["cz"]].astype(np.float64)
    k = rng.integers(0, sc.n_polys, n_near)
    # Project the centre onto a random face of its polytope, then jitter by mm to cm.
    first, count = sc.polys["first"].astype(int), sc.polys["count"].astype(int)
    rows = m[first[k] + rng.integers(0, 1 << 30, n_near) % count[k]]
    on_face = cs[k] - ((cs[k] * rows[:, :3]).sum(1) - rows[:, 3])[:, None] * rows[:, :3]
    near = on_face + rng.normal(size=(n_near, 3)) * 10.0 ** rng.uniform(-4, -1, (n_near, 1))
    far = rng.normal(size=(n - n_room - n_near, 3)) * 10.0 ** rng.uniform(1, 4, (n - n_room - n_near, 1))
    x = np.vstack([room, near, far]).astype(np.float32)
    goal = rng.uniform(0, 10, (n, 3)).astype(np.float32)
    return x, goal


def edge_states(sc) -> tuple[np.ndarray, np.ndarray]:
    """On a face, an edge and a vertex of a polytope, inside it, 1e4 m away, exactly at the
    goal, NaN and Inf in the position and in the goal, and out-of-range inputs."""
    m = sc.polytopes()[0].astype(np.float64)
    from scipy.spatial import HalfspaceIntersection

    c = np.array([sc.polys[0][k] for k in ("cx", "cy", "cz")], np.float64)
    verts = HalfspaceIntersection(np.c_[m[:, :3], -m[:, 3]], c).intersections
    face = c - ((c @ m[0, :3]) - m[0, 3]) * m[0, :3]
    edge = 0.5 * (verts[0] + verts[1])
    pts = [verts[0], verts[1], edge, face, c, 0.5 * (c + verts[0]), [1e4, 0, 0], [-1e4, 1e4, 1e4], [1e4, 1e4, 1e4],
           [99999.0, 0, 0], [1e5, 1e5, 1e5], [1.0000001e5, 0, 0], [np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf],
           [0, 0, 0], [5, 5, 1]]
    x = np.array(pts, np.float32)
    goal = np.tile(np.float32([5, 5, 1]), (len(x), 1))
    goal[0] = x[0]  # exactly at the goal, on a vertex
    goal[3] = x[3]  # exactly at the goal, on a face
    x2 = np.array([[5, 5, 1]] * 4, np.float32)
    g2 = np.array([[np.nan, 0, 0], [0, np.inf, 0], [2e5, 0, 0], [5, 5, 1]], np.float32)
    return np.vstack([x, x2]), np.vstack([goal, g2])


def assert_bitexact(ref: dict, out: np.ndarray, what: str) -> None:
    n = len(out)
    for f in FIELDS:
        a = np.ascontiguousarray(ref[f], np.float32).view(np.uint32).reshape(n, -1)
        b = np.ascontiguousarray(out[f], np.float32).view(np.uint32).reshape(n, -1)
        bad = np.nonzero(np.any(a != b, axis=1))[0]
        assert len(bad) == 0, (f"{what}: {f} differs in {len(bad)} of {n} states, first #{bad[0]}: "
                               f"C {b[bad[0]]} ref {a[bad[0]]}")
    bad = np.nonzero(ref["flags"] != out["flags"])[0]
    assert len(bad) == 0, f"{what}: flags differ in {len(bad)} states, first #{bad[0]}"


def arm_or_skip():
    import pytest

    from polycc.sim import kernel_arm

    miss = kernel_arm.missing_tools()
    if miss:
        msg = (f"ARM tests need {', '.join(miss)} (apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi "
               "qemu-system-arm)")
        if os.environ.get("POLYCC_REQUIRE_ARM") == "1":
            pytest.fail(msg + "; POLYCC_REQUIRE_ARM=1 forbids skipping")
        pytest.skip(msg)
    return kernel_arm




def indexed_scene(name: str, cap: float = 0.6, cell: float = 1.0, target_cycles: float | None = 30_000.0):
    """``scene(name)`` with a spatial index (octree refined towards ``target_cycles``)."""
    return _indexed(name, float(cap), float(cell), target_cycles)


@lru_cache(maxsize=None)
def _indexed(name, cap, cell, target):
    from polycc.onboard.index import build_index

    sc = scene(name)
    return sc.with_index(build_index(sc, cap, cell, target=target))


def index_states(sc, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Adversarial states for an indexed scene: grid points (cell corners) exactly and one float32 ulp
    either side, points on cell faces, the centres and corners of the leaves with the longest lists
    (near many polytopes), points just outside each face of the grid box B and far outside it."""
    rng = np.random.default_rng(seed)
    ix = sc.index
    o = np.asarray(ix.origin, np.float64)
    dims = np.array(ix.dims)
    s = ix.cell
    ijk = rng.integers(0, dims + 1, (n // 4, 3))
    corners = (o + ijk * s).astype(np.float32)
    ulp = np.nextafter(corners, np.float32(np.inf)), np.nextafter(corners, np.float32(-np.inf))
    faces = o + (ijk + rng.uniform(0, 1, (n // 4, 3)) * (rng.integers(0, 3, (n // 4, 1)) != np.arange(3))) * s
    # leaves with the longest lists: sample their boxes (corners, centres, random)
    work = ix.list_work(sc.polys["count"])
    lid, _ = sc.index_leaf(rng.uniform(o, o + dims * s, (20_000, 3)))
    busy = rng.uniform(o, o + dims * s, (20_000, 3))
    w = np.where(lid >= 0, work[np.maximum(lid, 0), 1], -1)
    near = busy[np.argsort(-w)[: n // 8]] + rng.normal(size=(n // 8, 3)) * 10.0 ** rng.uniform(-6, -2, (n // 8, 1))
    # outside B, just beyond every face and far
    hi = o + dims * s
    k = n // 8
    out = rng.uniform(o - 1, hi + 1, (k, 3))
    ax = rng.integers(0, 3, k)
    side = rng.integers(0, 2, k)
    step = 10.0 ** rng.uniform(-6, 0, k)
    out[np.arange(k), ax] = np.where(side, hi[ax] + step, o[ax] - step)
    x = np.vstack([corners, ulp[0], ulp[1], faces, near, out]).astype(np.float32)
    goal = rng.uniform(o, hi, (len(x), 3)).astype(np.float32)
    return x, goal
