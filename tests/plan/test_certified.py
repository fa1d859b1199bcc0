"""The certified lower bound LB of psi (polycc.plan.certified) against the float32 reference kernel:
never above psi, Lipschitz, the far-polytope tail and the grid field only lower it, and certified
segments really are clear."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.geometry.halfplanes import axis_box
from polycc.onboard.barrier import Params, barrier
from polycc.onboard.layout import pack_scene
from polycc.plan.certified import LIP, BarrierBound, certify_segment, near_segment
from polycc.plan.grid import Grid, field_reach, lower_field
from polycc.testing.synthetic import random_hull_polytopes


def scene(seed: int, n_hulls: int, n_boxes: int):
    rng = np.random.default_rng(seed)
    polys = random_hull_polytopes(rng, n_hulls, extent=(2.0, 2.0, 1.5), size=(0.05, 0.35)) if n_hulls else []
    for _ in range(n_boxes):
        lo = rng.uniform(0.0, 1.8, 3)
        polys.append(axis_box(lo, lo + rng.uniform(0.05, 0.8, 3)))
    return pack_scene(polys)


def probe_points(packed, rng, n: int) -> np.ndarray:
    """Points on, just inside and just outside the stored faces, plus uniform ones."""
    hs = packed.polytopes()
    out = [rng.uniform(-0.5, 2.5, size=(n, 3))]
    for h in hs[: min(len(hs), 6)]:
        h = h.astype(np.float64)
        c = rng.uniform(-0.5, 2.5, size=(n, 3))
        l = rng.integers(0, len(h), n)
        nrm, d = h[l, :3], h[l, 3]
        t = (d - np.sum(nrm * c, axis=1)) / np.sum(nrm * nrm, axis=1)
        out.append(c + t[:, None] * nrm + rng.normal(scale=0.02, size=(n, 1)) * nrm)
    return np.concatenate(out)


@settings(max_examples=40)
@given(seed=st.integers(0, 10_000), n_hulls=st.integers(0, 6), n_boxes=st.integers(0, 4),
       log_kappa=st.floats(0.0, 4.0), radius=st.floats(0.0, 0.5))
def test_lower_bound_never_above_psi(seed, n_hulls, n_boxes, log_kappa, radius):
    if n_hulls + n_boxes == 0:
        n_boxes = 1
    packed = scene(seed, n_hulls, n_boxes)
    kappa = float(np.float32(10.0**log_kappa))
    b = BarrierBound(packed, kappa, radius)
    p = probe_points(packed, np.random.default_rng(seed + 1), 200)
    psi, _, flags = barrier(packed, Params(kappa=kappa, radius=radius), p.astype(np.float32))
    lb = b.lower(p.astype(np.float32).astype(np.float64))
    ok = flags == 0
    assert ok.mean() > 0.9
    bad = np.flatnonzero(ok & (lb > psi.astype(np.float64)))
    assert len(bad) == 0, f"LB above psi at {len(bad)} points, worst by {np.max(lb[bad] - psi[bad]):.3g} m"


def test_lower_bound_is_tight_away_from_edges():
    """Far from every edge LB is below psi by about log(L)/kappa, no more (a useful bound)."""
    packed = pack_scene([axis_box((0, 0, 0), (1, 1, 1))])
    b = BarrierBound(packed, 100.0, 0.1)
    p = np.array([[0.5, 0.5, 1.4], [0.5, 1.6, 0.5], [-0.3, 0.5, 0.5]])
    psi, _, _ = barrier(packed, Params(kappa=100.0, radius=0.1), p.astype(np.float32))
    gap = psi - b.lower(p)
    assert np.all(gap >= 0) and np.all(gap <= math.log(6) / 100 + 1e-3)


@settings(max_examples=12)
@given(seed=st.integers(0, 10_000))
def test_lipschitz(seed):
    packed = scene(seed, 4, 2)
    b = BarrierBound(packed, 100.0, 0.1)
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 2.5, size=(300, 3))
    q = p + rng.normal(scale=0.05, size=p.shape)
    diff = np.abs(b.lower(p) - b.lower(q))
    assert np.all(diff <= LIP * np.linalg.norm(p - q, axis=1) + 1e-12)


@settings(max_examples=12)
@given(seed=st.integers(0, 10_000))
def test_tail_and_field_only_lower_it(seed):
    packed = scene(seed, 5, 2)
    b = BarrierBound(packed, 100.0, 0.1)
    rng = np.random.default_rng(seed)
    # tail: only the polytopes near a segment, the rest bounded
    a0, a1 = rng.uniform(-0.5, 2.5, 3), rng.uniform(-0.5, 2.5, 3)
    e = 0.3
    near = near_segment(b, a0, a1, e)
    pts = a0 + rng.uniform(0, 1, (100, 1)) * (a1 - a0)
    full, tail = b.lower(pts), b.lower(pts, near, e)
    assert np.all(tail <= full + 1e-12)
    capped = full < e - b.radius - 0.1
    assert np.all(full[capped] - tail[capped] < 1e-3)
    # grid field: a lower bound of LB at every cell centre
    g = Grid(np.array([-0.3, -0.3, -0.3]), 0.13, (22, 22, 15), np.zeros(0, np.float32), 0.05, 0.0)
    e = field_reach(b, g.need)
    f = lower_field(b, g.lo, g.spacing, g.shape, e)
    idx = np.stack(np.unravel_index(np.arange(f.size), f.shape), axis=1)
    exact = b.lower(g.centres(idx)).reshape(f.shape)
    assert np.all(f.astype(np.float64) <= exact)
    sel = exact < e - b.radius - 0.1
    assert np.all(exact[sel] - f[sel] < 2e-3)  # and close where it matters


@settings(max_examples=15)
@given(seed=st.integers(0, 10_000), req=st.floats(0.0, 0.2))
def test_certified_segments_are_clear(seed, req):
    packed = scene(seed, 5, 2)
    b = BarrierBound(packed, 100.0, 0.1)
    rng = np.random.default_rng(seed)
    for _ in range(5):
        a0, a1 = rng.uniform(-0.5, 2.5, 3), rng.uniform(-0.5, 2.5, 3)
        chk = certify_segment(b, a0, a1, req)
        pts = a0 + np.linspace(0, 1, 600)[:, None] * (a1 - a0)
        lb = b.lower(pts)
        if chk.ok:
            assert lb.min() >= req and chk.lower >= req
            psi, _, flags = barrier(packed, Params(kappa=100.0, radius=0.1), pts.astype(np.float32))
            assert np.all(psi[flags == 0] >= req - 1e-6)  # float32 points: within rounding of the segment
        elif lb.min() >= req + 0.01:
            pytest.fail(f"segment with LB >= {lb.min():.4f} not certified at {req:.4f}")


def test_tight_segment_bound_is_close_to_the_minimum():
    packed = pack_scene([axis_box((0, 0, 0), (1, 1, 1))])
    b = BarrierBound(packed, 100.0, 0.1)
    a0, a1 = np.array([-1.0, 0.5, 1.3]), np.array([2.0, 0.5, 1.3])
    chk = certify_segment(b, a0, a1, 0.0, tight=0.005)
    lb = b.lower(a0 + np.linspace(0, 1, 3001)[:, None] * (a1 - a0)).min()
    assert chk.ok and lb - 0.005 - 1e-9 <= chk.lower <= lb
