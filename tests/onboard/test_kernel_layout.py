"""The scene layout (format 3): Python records match the C structs byte for byte, the image
round-trips, the byte formula is exact, the quantized (decoded) polytopes contain the exact
ones (outward rounding, checked in exact rational arithmetic), the certified per-polytope bounds
are built correctly, and bad input is refused clearly."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.errors import PolyccError
from polycc.geometry.halfplanes import axis_box, hull_halfplanes, polytope_vertices
from polycc.onboard.layout import (
    CLUSTER_BYTES,
    CLUSTER_DTYPE,
    NORMAL_BYTES,
    NORMAL_DTYPE,
    PLANE_BYTES,
    PLANE_DTYPE,
    POLY_BYTES,
    POLY_DTYPE,
    ROOT_BYTES,
    SCENE_FORMAT,
    layout_bytes,
    n_clusters_for,
    pack_scene,
    scene_from_bytes,
)
from polycc.testing.synthetic import pad_to_planes, random_hull_polytopes

kffi = pytest.importorskip("polycc.sim.kernel_ffi")


def test_records_match_the_c_structs():
    ffi = kffi.load().ffi
    for cname, dt, size in (("polycc_plane_t", PLANE_DTYPE, PLANE_BYTES), ("polycc_poly_t", POLY_DTYPE, POLY_BYTES),
                            ("polycc_cluster_t", CLUSTER_DTYPE, CLUSTER_BYTES),
                            ("polycc_normal_t", NORMAL_DTYPE, NORMAL_BYTES)):
        assert ffi.sizeof(cname) == size == dt.itemsize, cname
        for name in dt.names:
            assert ffi.offsetof(cname, name) == dt.fields[name][1], (cname, name)


def test_cdef_matches_the_header():
    """The cffi declarations copy the header's structs; cffi's API mode checks every declared
    field against the real header when it compiles, so here only the macros are compared."""
    text = (kffi.SRC / "polycc_scene_layout.h").read_text()
    assert f"#define POLYCC_SCENE_FORMAT {SCENE_FORMAT}u" in text
    for macro, v in (("POLY", POLY_BYTES), ("PLANE", PLANE_BYTES), ("CLUSTER", CLUSTER_BYTES),
                     ("NORMAL", NORMAL_BYTES), ("ROOT", ROOT_BYTES)):
        assert f"#define POLYCC_{macro}_BYTES {v}u" in text


def _rational_max_violation(h: np.ndarray, verts: np.ndarray) -> Fraction:
    """max over planes and vertices of n . v - d, exactly (float32/float64 values as rationals)."""
    H = [[Fraction(float(x)) for x in row] for row in h]
    worst = None
    for v in verts:
        fv = [Fraction(float(x)) for x in v]
        for r in H:
            g = r[0] * fv[0] + r[1] * fv[1] + r[2] * fv[2] - r[3]
            worst = g if worst is None or g > worst else worst
    return worst


def _check_contains(sc, verts_in_input_order):
    for k, h in enumerate(sc.polytopes()):
        v = verts_in_input_order[sc.order[k]]
        assert _rational_max_violation(h, v) <= 0, f"packed polytope {k} does not contain its vertices"
        # unit-or-shorter normals, exactly
        for row in h:
            assert sum(Fraction(float(x)) ** 2 for x in row[:3]) <= 1


def test_image_round_trip_and_decode():
    rng = np.random.default_rng(0)
    polys = random_hull_polytopes(rng, 23)
    sc = pack_scene(polys)
    back = scene_from_bytes(sc.to_bytes())
    assert back.to_bytes() == sc.to_bytes()
    assert len(sc.to_bytes()) == sc.flash_bytes() - 20  # minus the five pointers of the root struct
    assert sorted(sc.order.tolist()) == list(range(23))
    for a, b in zip(back.polytopes(), sc.polytopes()):
        assert np.array_equal(a, b)
    assert np.array_equal(back.polys, sc.polys)
    # the decoded polytopes contain the input ones, and are close to them
    verts = [polytope_vertices(h) for h in polys]
    _check_contains(sc, verts)
    # clusters cover the polytopes in order, planes are contiguous
    firsts = sc.clusters["first"].astype(int)
    counts = sc.clusters["count"].astype(int)
    assert firsts[0] == 0 and np.all(firsts[1:] == np.cumsum(counts)[:-1]) and counts.sum() == 23
    assert np.all(sc.polys["first"][1:] == np.cumsum(sc.polys["count"])[:-1])


def test_layout_bytes_is_exact():
    rng = np.random.default_rng(3)
    for n in (1, 5, 23, 64, 101):
        sc = pack_scene(random_hull_polytopes(rng, n, points=(5, 9)))
        assert sc.n_clusters == n_clusters_for(n)
        assert sc.flash_bytes() == layout_bytes(sc.n_polys, sc.n_planes, n_clusters_for(n), sc.n_normals)
        assert sc.flash_bytes() == ROOT_BYTES + len(sc.to_bytes()) - 32
    assert layout_bytes(1000, 8000, 32, 400) == 52 + 4 * 8000 + 16 * 1000 + 32 * 32 + 12 * 400


def test_lead_planes_face_their_octant():
    sc = pack_scene([axis_box([0, 0, 0], [1, 2, 3])])
    h = sc.polytopes()[0]
    for o, lead in enumerate(sc.polys[0]["lead"]):
        s = np.array([-1.0 if o & (1 << i) else 1.0 for i in range(3)])
        assert lead < 8 and h[lead, :3] @ s == np.max(h[:, :3] @ s)


def test_box_bounds_are_the_textbook_values():
    sc = pack_scene([axis_box([-1, -1, -1], [1, 1, 1])])
    P = sc.polys[0]
    assert np.allclose([P["cx"], P["cy"], P["cz"]], 0, atol=1e-6)
    assert np.sqrt(3) <= P["inv_gamma"] <= np.sqrt(3) + 2**-8 + 1e-6
    assert np.sqrt(3) <= P["r_out"] <= np.sqrt(3) * (1 + 1e-5) + 16 * float(sc.quantum)
    assert 1.0 - float(sc.quantum) <= P["r_in"] <= 1.0
    # a box with binary coordinates is stored exactly
    assert np.array_equal(np.sort(sc.polytopes()[0], axis=0), np.sort(axis_box([-1, -1, -1], [1, 1, 1]), axis=0))


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
        assert np.array_equal(np.max(x @ a[:, :3].T - a[:, 3], axis=1) <= 0,
                              np.max(x @ b[:, :3].T - b[:, 3], axis=1) <= 0)
    assert pack_scene(padded, merge_duplicates=False).n_planes == 200
    assert pack_scene(padded).n_planes == sum(len(h) for h in polys)


def _voxel_hull(rng, vox):
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    c = rng.uniform(-3, 3, 3)
    pts = np.round((c + rng.normal(size=(int(rng.integers(1, 8)), 3)) * rng.uniform(0.02, 0.5, 3)) / vox)
    return (pts[:, None, :] + corners[None]).reshape(-1, 3) * vox


@settings(max_examples=40)
@given(st.integers(0, 2**31), st.integers(1, 6), st.sampled_from([0.05, 0.1, 0.0437]),
       st.sampled_from([None, 4096, 16, 3]), st.sampled_from([None, 8, 24]), st.booleans())
def test_packed_polytopes_contain_the_exact_ones(seed, n, vox, grid, max_normals, give_vertices):
    """Outward rounding: every vertex of every exact polytope satisfies every decoded half-plane,
    in exact rational arithmetic, whatever the normal snapping and table cap."""
    rng = np.random.default_rng(seed)
    verts = [_voxel_hull(rng, vox) for _ in range(n)]
    hs = [hull_halfplanes(v) for v in verts]
    if not give_vertices:  # vertices computed by qhull from the half-planes
        verts = [polytope_vertices(h) for h in hs]
    sc = pack_scene(hs, verts if give_vertices else None, normal_grid=grid, max_normals=max_normals)
    _check_contains(sc, verts)
    if max_normals is not None:
        assert sc.n_normals <= max(max_normals, 6)
    assert sc.flash_bytes() == layout_bytes(sc.n_polys, sc.n_planes, sc.n_clusters, sc.n_normals)


def test_lattice_covers_meet_the_storage_target():
    """Voxel-corner hulls with the table capped: <= 8 bytes per half-plane, every byte counted."""
    rng = np.random.default_rng(5)
    verts = [_voxel_hull(rng, 0.05) for _ in range(120)]
    sc = pack_scene([hull_halfplanes(v) for v in verts], verts, max_normals=256)
    assert sc.bytes_per_plane() <= 8.0, sc.bytes_per_plane()


def test_quantization_is_tight():
    """The stored polytopes grow by little: support distance over the original <= 2 quanta plus the
    normal snapping (4096 grid)."""
    rng = np.random.default_rng(2)
    polys = random_hull_polytopes(rng, 10)
    sc = pack_scene(polys)
    q = float(sc.quantum)
    for k, h in enumerate(sc.polytopes()):
        v = polytope_vertices(polys[sc.order[k]])
        h = h.astype(np.float64)
        excess = h[:, 3] - np.max(v @ h[:, :3].T, axis=0)
        assert np.all(excess >= 0) and np.all(excess <= 1.01 * q)


@pytest.mark.parametrize("bad, msg", [
    ([], "no polytopes"),
    ([np.array([[2.0, 0, 0, 1]] * 4)], "unit length"),
    ([np.array([[1.0, 0, 0, 1], [-1.0, 0, 0, 1], [0, 1.0, 0, 1]])], "unbounded|empty"),
    ([np.array([[1.0, 0, 0, 1], [-1.0, 0, 0, 1], [0, 1.0, 0, 1], [0, -1.0, 0, 1], [0, 0.6, 0.8, 1]])], "unbounded"),
    ([axis_box([0, 0, 0], [1, 1, 1])[[0, 1, 2, 3, 4, 5] * 50]], "split it"),
    ([np.array([[1.0, 0, 0, np.nan]] * 4)], "non-finite"),
])
def test_bad_polytopes_are_refused(bad, msg):
    with pytest.raises(PolyccError, match=msg):
        pack_scene(bad)


def test_bad_quantum_and_vertices_are_refused():
    box = axis_box([0, 0, 0], [1, 1, 1])
    with pytest.raises(PolyccError, match="power of two"):
        pack_scene([box], quantum=0.001)
    with pytest.raises(PolyccError, match="vertex sets"):
        pack_scene([box], [])
    with pytest.raises(PolyccError, match="int16"):
        pack_scene([axis_box([0, 0, 0], [1000, 1, 1])], quantum=2.0**-10)


def test_over_elongated_polytope_is_closed_by_its_box():
    """Regression (hypothesis, test_kernel_properties): a random sliver hull had 1/gamma ~ 1600,
    beyond the record's uint16 field, and pack_scene refused the scene. It now adds the
    polytope's axis-aligned bounding box, which still contains the exact polytope."""
    from polycc.geometry.halfplanes import inv_gamma as _inv_gamma
    from polycc.onboard.layout import _MAX_INV_GAMMA

    rng = np.random.default_rng(2492)
    polys = random_hull_polytopes(rng, 6, extent=(4.0, 4.0, 4.0), size=(0.05, 1.0), points=(5, 25))
    assert _inv_gamma(polys[5][:, :3]) > 2 * _MAX_INV_GAMMA  # the case: beyond 65535 / 256
    sliver = polys[5]
    sc = pack_scene([sliver])
    stored = sc.polytopes()[0].astype(np.float64)
    assert len(stored) > len(sliver)  # box planes added
    verts = polytope_vertices(sliver)
    assert np.all(verts @ stored[:, :3].T <= stored[:, 3] + 1e-12)  # still contains the exact polytope
    assert sc.polys["inv_gamma"][0] <= 2.0  # sqrt(3) plus the rounding


def _snap_by_definition(n, grid):
    """snap_normal as first written (the specification): m = round(K n) / gcd, m / |m| in float64, then
    float32 shrunk toward 0 until |f|^2 <= 1 in exact rational arithmetic."""
    m = np.rint(np.asarray(n, np.float64) * grid).astype(np.int64)
    g = int(np.gcd.reduce(np.abs(m))) or 1
    m //= g
    f = (m / np.sqrt(float(m @ m))).astype(np.float32)
    while sum(Fraction(float(x)) ** 2 for x in f) > 1:
        i = int(np.argmax(np.abs(f)))
        f[i] = np.nextafter(f[i], np.float32(0))
    return ("m", *map(int, m)), f


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).filter(lambda t: sum(x * x for x in t) > 1e-3),
                min_size=1, max_size=30), st.sampled_from([16, 4096]))
def test_vectorised_snapping_is_the_scalar_definition(rows, grid):
    """Regression for the speed-up of the normal table (one exact check per lattice direction, cached): every
    key and float32 bit pattern is the definition's, and |f|^2 <= 1 holds exactly."""
    from polycc.onboard.layout import snap_normal, snap_normals

    n = np.array(rows, np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    keys, f = snap_normals(n, grid)
    for i, row in enumerate(n):
        key, want = _snap_by_definition(row, grid)
        assert keys[i] == key == snap_normal(row, grid)[0]
        assert f[i].view(np.uint32).tolist() == want.view(np.uint32).tolist()
        assert snap_normal(row, grid)[1].view(np.uint32).tolist() == want.view(np.uint32).tolist()
        assert sum(Fraction(float(x)) ** 2 for x in f[i]) <= 1
