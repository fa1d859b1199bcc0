"""The 3DGS .ply writer: layout, activations, quaternions, point clouds, and the loader round trip."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData

from polycc.errors import PolyccError
from polycc.scene.ellipsoids import Ellipsoids, quaternion_to_rotation
from polycc.scene.writers import (
    GAUSSIAN_PLY_PROPERTIES,
    SH_C0,
    rotation_to_quaternion,
    write_gaussian_ply,
    write_point_ply,
)


def random_ellipsoids(n: int = 500, seed: int = 0) -> Ellipsoids:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Ellipsoids(
        centers=rng.uniform(-5, 5, size=(n, 3)),
        rotations=quaternion_to_rotation(q),
        sigmas=np.exp(rng.uniform(np.log(1e-4), np.log(0.5), size=(n, 3))),
        k=1.0,
        opacity=rng.uniform(0.0, 1.0, size=n).astype(np.float32),
        colors=rng.integers(0, 256, size=(n, 3)).astype(np.uint8),
    )


def covariances(ell: Ellipsoids) -> np.ndarray:
    L = ell.rotations * ell.sigmas[:, None, :]
    return L @ np.swapaxes(L, 1, 2)


def expected_names() -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


@pytest.mark.parametrize("binary", [True, False])
def test_layout_is_graphdeco(tmp_path, binary):
    ell = random_ellipsoids(50)
    path = tmp_path / "g.ply"
    write_gaussian_ply(path, ell, binary=binary)
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names == expected_names() == list(GAUSSIAN_PLY_PROPERTIES)
    assert len(names) == 62
    assert all(v.data.dtype[n] == np.dtype("<f4") or v.data.dtype[n] == np.dtype("f4") for n in names)
    assert ply.text is (not binary)
    if binary:
        assert ply.byte_order == "<"
    assert v.count == 50
    for n in ["nx", "ny", "nz"] + [f"f_rest_{i}" for i in range(45)]:
        assert np.all(v[n] == 0)


@pytest.mark.parametrize("binary", [True, False])
def test_activation_round_trip(tmp_path, binary):
    ell = random_ellipsoids(400, seed=1)
    path = tmp_path / "g.ply"
    write_gaussian_ply(path, ell, binary=binary)
    v = PlyData.read(str(path))["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    np.testing.assert_allclose(xyz, ell.centers, rtol=0, atol=1e-6)
    sig = np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], axis=1).astype(np.float64))
    np.testing.assert_allclose(sig, ell.sigmas, rtol=1e-5)
    alpha = 1.0 / (1.0 + np.exp(-v["opacity"].astype(np.float64)))
    np.testing.assert_allclose(alpha, ell.opacity, atol=1e-6)
    q = np.stack([v[f"rot_{i}"] for i in range(4)], axis=1).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    R = quaternion_to_rotation(q / np.linalg.norm(q, axis=1, keepdims=True))
    np.testing.assert_allclose(R, ell.rotations, atol=1e-6)
    dc = np.stack([v[f"f_dc_{i}"] for i in range(3)], axis=1).astype(np.float64)
    rgb = np.round((0.5 + SH_C0 * dc) * 255.0)
    np.testing.assert_array_equal(rgb, ell.colors)


def test_ascii_equals_binary(tmp_path):
    ell = random_ellipsoids(300, seed=2)
    write_gaussian_ply(tmp_path / "b.ply", ell, binary=True)
    write_gaussian_ply(tmp_path / "a.ply", ell, binary=False)
    a = PlyData.read(str(tmp_path / "a.ply"))["vertex"].data
    b = PlyData.read(str(tmp_path / "b.ply"))["vertex"].data
    for n in GAUSSIAN_PLY_PROPERTIES:
        np.testing.assert_array_equal(a[n], b[n])


def test_quaternion_special_rotations():
    Rs = np.array(
        [
            np.eye(3),
            np.diag([1.0, -1.0, -1.0]),  # half turns: w = 0
            np.diag([-1.0, 1.0, -1.0]),
            np.diag([-1.0, -1.0, 1.0]),
            [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],  # half turn about (1,1,0)/sqrt2
        ]
    )
    q = rotation_to_quaternion(Rs)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(quaternion_to_rotation(q), Rs, atol=1e-12)


def test_quaternion_random_and_reflections():
    ell = random_ellipsoids(2000, seed=3)
    q = rotation_to_quaternion(ell.rotations)
    np.testing.assert_allclose(quaternion_to_rotation(q), ell.rotations, atol=1e-12)
    # A reflection (det -1) is written as a rotation describing the same ellipsoid.
    refl = ell.rotations.copy()
    refl[:, :, 1] *= -1
    back = Ellipsoids(ell.centers, quaternion_to_rotation(rotation_to_quaternion(refl)), ell.sigmas)
    np.testing.assert_allclose(covariances(back), covariances(ell), atol=1e-12)


def test_extreme_opacity_and_missing_fields(tmp_path):
    ell = random_ellipsoids(4)
    ell.opacity = np.array([0.0, 1.0, 0.5, 1e-9], dtype=np.float32)
    write_gaussian_ply(tmp_path / "o.ply", ell)
    v = PlyData.read(str(tmp_path / "o.ply"))["vertex"]
    assert np.all(np.isfinite(v["opacity"]))
    alpha = 1.0 / (1.0 + np.exp(-v["opacity"].astype(np.float64)))
    np.testing.assert_allclose(alpha, [0.0, 1.0, 0.5, 0.0], atol=2e-6)

    bare = Ellipsoids(ell.centers, ell.rotations, ell.sigmas)  # no opacity, no colours
    write_gaussian_ply(tmp_path / "bare.ply", bare)
    v = PlyData.read(str(tmp_path / "bare.ply"))["vertex"]
    assert np.all(v["f_dc_0"] == 0) and np.all(v["opacity"] > 10)


def test_bad_input_raises(tmp_path):
    ell = random_ellipsoids(3)
    with pytest.raises(PolyccError, match="no ellipsoids"):
        write_gaussian_ply(tmp_path / "e.ply", ell.subset(np.zeros(3, bool)))
    ell.sigmas[1, 2] = 0.0
    with pytest.raises(PolyccError, match="sigmas"):
        write_gaussian_ply(tmp_path / "z.ply", ell)
    (tmp_path / "file").write_text("")
    with pytest.raises(PolyccError, match="cannot write"):
        write_gaussian_ply(tmp_path / "file" / "x.ply", random_ellipsoids(3))


@pytest.mark.parametrize("binary", [True, False])
def test_point_ply(tmp_path, binary):
    pts = np.random.default_rng(0).uniform(-1, 1, size=(100, 3))
    write_point_ply(tmp_path / "p.ply", pts, binary=binary)
    v = PlyData.read(str(tmp_path / "p.ply"))["vertex"]
    assert [p.name for p in v.properties] == ["x", "y", "z"]
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), pts, atol=1e-6)

    write_point_ply(tmp_path / "r.ply", pts, radius=0.05, binary=binary)
    v = PlyData.read(str(tmp_path / "r.ply"))["vertex"]
    assert [p.name for p in v.properties] == ["x", "y", "z", "radius"]
    np.testing.assert_allclose(v["radius"], 0.05)

    radii = np.linspace(0.01, 0.1, 100)
    write_point_ply(tmp_path / "rr.ply", pts, radius=radii, binary=binary)
    np.testing.assert_allclose(PlyData.read(str(tmp_path / "rr.ply"))["vertex"]["radius"], radii, rtol=1e-6)


@pytest.mark.parametrize("binary", [True, False])
def test_load_scene_round_trip(tmp_path, binary):
    scene = pytest.importorskip("polycc.scene.load")
    ell = random_ellipsoids(300, seed=4)
    path = tmp_path / "g.ply"
    write_gaussian_ply(path, ell, binary=binary)
    got = scene.load_scene(path, scene.SceneOptions()).ellipsoids
    assert len(got) == len(ell)
    np.testing.assert_allclose(got.centers, ell.centers, atol=1e-6)
    np.testing.assert_allclose(got.sigmas, ell.sigmas, rtol=1e-5)
    # float32 quaternions: each covariance is exact to ~1e-6 of its largest eigenvalue.
    scale = (ell.sigmas.max(axis=1) ** 2)[:, None, None]
    np.testing.assert_allclose(covariances(got) / scale, covariances(ell) / scale, rtol=0, atol=1e-5)
    np.testing.assert_allclose(got.opacity, ell.opacity, atol=1e-6)
    if got.colors is not None:  # colours are for plots; the reader may truncate instead of round
        assert np.abs(got.colors.astype(int) - ell.colors.astype(int)).max() <= 1


def test_load_scene_reads_point_ply(tmp_path):
    scene = pytest.importorskip("polycc.scene.load")
    pts = np.random.default_rng(5).uniform(-1, 1, size=(50, 3))
    write_point_ply(tmp_path / "r.ply", pts, radius=0.03)
    got = scene.load_scene(tmp_path / "r.ply", scene.SceneOptions()).ellipsoids
    np.testing.assert_allclose(got.centers, pts, atol=1e-6)
    # A point with radius r is (at least) the ball of radius r.
    assert np.all(got.k * got.sigmas >= 0.03 * (1 - 1e-6))
