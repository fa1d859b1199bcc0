"""The scene layout: Python records match the C structs byte for byte, the image round-trips,
the certified per-polytope bounds are built correctly, and bad input is refused clearly."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.errors import PolyccError
from polycc.scene_layout import (
    CLUSTER_BYTES, PLANE_BYTES, PLANE_DTYPE, POLY_BYTES, POLY_DTYPE, SCENE_FORMAT, axis_box, hull_halfplanes, pack_scene,
    pad_to_planes, random_hull_polytopes, scene_from_bytes,
)

kffi = pytest.importorskip("host_sim.kernel_ffi")


def test_records_match_the_c_structs():
    ffi = kffi.load().ffi
    assert ffi.sizeof("polycc_plane_t") == PLANE_BYTES == PLANE_DTYPE.itemsize
    assert ffi.sizeof("polycc_poly_t") == POLY_BYTES == CLUSTER_BYTES == POLY_DTYPE.itemsize
    for name in POLY_DTYPE.names:
        assert ffi.offsetof("polycc_poly_t", name) == POLY_DTYPE.fields[name][1], name
    for name in PLANE_DTYPE.names:
        assert ffi.offsetof("polycc_plane_t", name) == PLANE_DTYPE.fields[name][1], name


def test_cdef_matches_the_header():
    """The cffi declarations copy the header's structs; cffi's API mode checks every declared
    field against the real header when it compiles, so here only the macros are compared."""
    text = (kffi.SRC / "polycc_scene_layout.h").read_text()
    assert f"#define POLYCC_SCENE_FORMAT {SCENE_FORMAT}u" in text
    assert f"#define POLYCC_POLY_BYTES {POLY_BYTES}u" in text and f"#define POLYCC_PLANE_BYTES {PLANE_BYTES}u" in text


def test_image_round_trip_and_decode():
    rng = np.random.default_rng(0)
    polys = random_hull_polytopes(rng, 23)
    sc = pack_scene(polys)
    back = scene_from_bytes(sc.to_bytes())
    assert back.to_bytes() == sc.to_bytes()
    assert len(sc.to_bytes()) == sc.flash_bytes() - 12  # minus the three pointers of the root struct
    assert sorted(sc.order.tolist()) == list(range(23))
    for k, h in enumerate(sc.polytopes()):
        assert np.array_equal(h, polys[sc.order[k]].astype(np.float32))
    # clusters cover the polytopes in order
    firsts = sc.clusters["first"].astype(int)
    counts = sc.clusters["count"].astype(int)
    assert firsts[0] == 0 and np.all(firsts[1:] == np.cumsum(counts)[:-1]) and counts.sum() == 23
    assert np.all(sc.polys["first"][1:] == np.cumsum(sc.polys["count"])[:-1])


def test_lead_planes_face_their_octant():
    sc = pack_scene([axis_box([0, 0, 0], [1, 2, 3])])
    h = sc.polytopes()[0]
    for o, lead in enumerate(sc.polys[0]["lead"]):
        s = np.array([-1.0 if o & (1 << i) else 1.0 for i in range(3)])
        assert h[lead, :3] @ s == np.max(h[:, :3] @ s)


def test_box_bounds_are_the_textbook_values():
    sc = pack_scene([axis_box([-1, -1, -1], [1, 1, 1])])
    P = sc.polys[0]
    assert np.allclose([P["cx"], P["cy"], P["cz"]], 0, atol=1e-6)
    assert np.isclose(P["inv_gamma"], np.sqrt(3), rtol=1e-5) and P["inv_gamma"] >= np.float32(np.sqrt(3)) * (1 - 1e-7)
    assert np.isclose(P["r_out"], np.sqrt(3), rtol=1e-5) and np.isclose(P["r_in"], 1.0, rtol=1e-5)
    assert P["r_in"] <= 1.0


def test_hull_merges_coplanar_facets():
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    h = hull_halfplanes(cube)
    assert len(h) == 6
    assert np.allclose(np.linalg.norm(h[:, :3], axis=1), 1)


def test_padding_keeps_the_polytopes():
    rng = np.random.default_rng(1)
    polys = random_hull_polytopes(rng, 5)
    padded = pad_to_planes(polys, 200)
    assert sum(len(h) for h in padded) == 200
    x = rng.uniform(-1, 11, (2000, 3))
    for a, b in zip(polys, padded):
        assert np.array_equal(np.max(x @ a[:, :3].T - a[:, 3], axis=1) <= 0, np.max(x @ b[:, :3].T - b[:, 3], axis=1) <= 0)


@pytest.mark.parametrize("bad, msg", [
    ([], "no polytopes"),
    ([np.array([[2.0, 0, 0, 1]] * 4)], "unit length"),
    ([np.array([[1.0, 0, 0, 1], [-1.0, 0, 0, 1], [0, 1.0, 0, 1]])], "unbounded|empty"),
    ([axis_box([0, 0, 0], [1, 1, 1])[[0, 1, 2, 3, 4, 5] * 50]], "split it"),
    ([np.array([[1.0, 0, 0, np.nan]] * 4)], "non-finite"),
])
def test_bad_polytopes_are_refused(bad, msg):
    with pytest.raises(PolyccError, match=msg):
        pack_scene(bad)
