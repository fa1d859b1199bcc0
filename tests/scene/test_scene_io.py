"""Scene ingest: formats, activations, transforms, filters and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polycc.cli import main
from polycc.scene.load import SceneOptions, load_scene
from polycc.testing.files import gaussian_columns, write_ply


def test_gaussian_ply_activations(tmp_path):
    cols = {k: v.astype(np.float32).astype(np.float64) for k, v in gaussian_columns(50).items()}
    p = write_ply(tmp_path / "g.ply", cols)
    s = load_scene(p)
    e = s.ellipsoids
    assert s.stats.read == s.stats.kept == 50
    # sigma = exp(scale) as a set per splat (order of axes is the rotation's columns)
    expect = np.exp(np.stack([cols[f"scale_{i}"] for i in range(3)], 1))
    np.testing.assert_allclose(np.sort(e.sigmas, 1), np.sort(expect, 1), rtol=1e-6)
    np.testing.assert_allclose(e.opacity, 1 / (1 + np.exp(-cols["opacity"])), rtol=1e-5)
    # covariance = R S S^T R^T with the normalised quaternion
    q = np.stack([cols[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    q /= np.linalg.norm(q, axis=1)[:, None]
    w, x, y, z = q.T
    R0 = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]).transpose(2, 0, 1)
    S = np.exp(np.stack([cols[f"scale_{i}"] for i in range(3)], 1).astype(np.float64))
    cov_ref = np.einsum("nij,nj,nkj->nik", R0, S**2, R0)
    cov = np.einsum("nij,nj,nkj->nik", e.rotations, e.sigmas**2, e.rotations)
    np.testing.assert_allclose(cov, cov_ref, rtol=1e-5, atol=1e-12)


def test_property_order_and_extra_properties_do_not_matter(tmp_path):
    cols = gaussian_columns(20, seed=3)
    shuffled = {k: cols[k] for k in ["rot_2", "scale_1", "z", "opacity", "rot_0", "x", "scale_2", "rot_3", "y",
                                     "scale_0", "rot_1"]}
    shuffled["nx"] = np.zeros(20)
    shuffled["f_dc_0"] = np.ones(20)
    a = load_scene(write_ply(tmp_path / "a.ply", cols)).ellipsoids
    b = load_scene(write_ply(tmp_path / "b.ply", shuffled)).ellipsoids
    np.testing.assert_array_equal(a.centers, b.centers)
    np.testing.assert_array_equal(a.sigmas, b.sigmas)


def test_ascii_ply_equals_binary(tmp_path):
    cols = gaussian_columns(10, seed=5)
    a = load_scene(write_ply(tmp_path / "a.ply", cols)).ellipsoids
    b = load_scene(write_ply(tmp_path / "b.ply", cols, text=True)).ellipsoids
    np.testing.assert_allclose(a.centers, b.centers, rtol=1e-6)
    np.testing.assert_allclose(a.sigmas, b.sigmas, rtol=1e-5)


def test_point_cloud_with_and_without_radius(tmp_path):
    pts = {"x": np.array([0.0, 1.0]), "y": np.array([0.0, 0.0]), "z": np.array([0.0, 0.0])}
    s = load_scene(write_ply(tmp_path / "p.ply", pts), SceneOptions(sigma=3.0))
    assert s.stats.kept == 2 and s.stats.sigma_floored == 2
    pts["radius"] = np.array([0.1, 0.2])
    e = load_scene(write_ply(tmp_path / "r.ply", pts), SceneOptions(sigma=3.0)).ellipsoids
    # the radius is the extent whatever --sigma is
    np.testing.assert_allclose(e.aabb_halfwidth(), [[0.1] * 3, [0.2] * 3], rtol=1e-6)


def test_real_scenes_load(scenes_dir):
    d = load_scene(scenes_dir / "donut_fused.ply")
    assert d.stats.read == 45_624
    p = load_scene(scenes_dir / "plant.splat", SceneOptions(min_opacity=0.5))
    assert p.stats.read == 113_648
    assert p.stats.filtered_opacity + p.stats.kept == p.stats.read and p.stats.filtered_opacity > 0
    assert np.allclose(np.linalg.det(p.ellipsoids.rotations), 1.0)


def test_transform_similarity_and_matrix(tmp_path):
    cols = gaussian_columns(30, seed=7)
    p = write_ply(tmp_path / "g.ply", cols)
    base = load_scene(p).ellipsoids
    (tmp_path / "sim.json").write_text(json.dumps({"scale": 2.0, "rotation": [0, 0, 0, 1], "translation": [1, 2, 3]}))
    from polycc.scene.transform import load_transform
    T = load_transform(tmp_path / "sim.json")
    e = load_scene(p, SceneOptions(transform=T)).ellipsoids
    Rz = np.diag([-1.0, -1.0, 1.0])
    np.testing.assert_allclose(e.centers, 2 * base.centers @ Rz.T + [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(e.sigmas, 2 * base.sigmas, rtol=1e-12)
    # a general (shearing) affine matrix: covariance maps as A Sigma A^T
    A = np.array([[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.3, 0.0, 0.5]])
    T = np.eye(4)
    T[:3, :3] = A
    (tmp_path / "m.json").write_text(json.dumps({"matrix": T.tolist()}))
    e2 = load_scene(p, SceneOptions(transform=load_transform(tmp_path / "m.json"), scale=0.5)).ellipsoids
    cov0 = np.einsum("nij,nj,nkj->nik", base.rotations, base.sigmas**2, base.rotations)
    cov2 = np.einsum("nij,nj,nkj->nik", e2.rotations, e2.sigmas**2, e2.rotations)
    B = 0.5 * A
    np.testing.assert_allclose(cov2, B @ cov0 @ B.T, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(e2.rotations), 1.0)


def test_crop_keeps_straddling_ellipsoids(tmp_path):
    cols = {"x": np.array([0.0, 0.95, 3.0]), "y": np.zeros(3), "z": np.zeros(3), "opacity": np.full(3, 5.0),
            "scale_0": np.log([0.1, 0.1, 0.1]), "scale_1": np.log([0.1, 0.1, 0.1]), "scale_2": np.log([0.1, 0.1, 0.1]),
            "rot_0": np.ones(3), "rot_1": np.zeros(3), "rot_2": np.zeros(3), "rot_3": np.zeros(3)}
    s = load_scene(write_ply(tmp_path / "c.ply", cols), SceneOptions(crop=(-1, -1, -1, 0.9, 1, 1)))
    assert s.stats.kept == 2 and s.stats.cropped == 1  # the one at x=0.95 (radius 0.1) straddles x=0.9


@pytest.mark.parametrize("case", ["truncated", "no_xyz", "no_scale", "no_rot", "nan", "zero_quat", "empty_after",
                                  "ext", "missing", "splat_trunc"])
def test_bad_input_is_one_line_error_exit_2(tmp_path, capsys, case):
    cols = gaussian_columns(40, seed=1)
    extra: list[str] = []
    if case == "truncated":
        p = write_ply(tmp_path / "t.ply", cols)
        data = p.read_bytes()
        p.write_bytes(data[: len(data) - 100])
    elif case == "no_xyz":
        del cols["y"]
        p = write_ply(tmp_path / "t.ply", cols)
    elif case == "no_scale":
        del cols["scale_2"]
        p = write_ply(tmp_path / "t.ply", cols)
    elif case == "no_rot":
        del cols["rot_0"]
        p = write_ply(tmp_path / "t.ply", cols)
    elif case == "nan":
        cols["x"][3] = np.nan
        cols["scale_1"][5] = np.inf
        p = write_ply(tmp_path / "t.ply", cols)
    elif case == "zero_quat":
        for i in range(4):
            cols[f"rot_{i}"][7] = 0.0
        p = write_ply(tmp_path / "t.ply", cols)
    elif case == "empty_after":
        p = write_ply(tmp_path / "t.ply", cols)
        extra = ["--crop", "10,10,10,11,11,11"]
    elif case == "ext":
        p = tmp_path / "t.obj"
        p.write_text("v 0 0 0\n")
    elif case == "missing":
        p = tmp_path / "nope.ply"
    elif case == "splat_trunc":
        p = tmp_path / "t.splat"
        p.write_bytes(b"\0" * 33)
    rc = main(["voxelize", str(p), "-o", str(tmp_path / "o.npz"), *extra])
    err = capsys.readouterr().err
    assert rc == 2
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(p.name) in lines[0], err
    if case == "nan":
        assert "2 splats" in err and "--drop-invalid" in err


def test_drop_invalid_counts_what_it_drops(tmp_path):
    cols = gaussian_columns(40, seed=1)
    cols["x"][3] = np.nan
    for i in range(4):
        cols[f"rot_{i}"][7] = 0.0
    s = load_scene(write_ply(tmp_path / "t.ply", cols), SceneOptions(drop_invalid=True))
    st = s.stats
    assert (st.read, st.invalid, st.invalid_nonfinite, st.invalid_quaternion, st.kept) == (40, 2, 1, 1, 38)


def test_splat_reader(tmp_path):
    rec = np.zeros(3, dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    rec["pos"] = [[0, 0, 0], [1, 2, 3], [-1, 0, 1]]
    rec["scale"] = 0.01
    rec["rgba"] = [[255, 0, 0, 255], [0, 255, 0, 128], [0, 0, 255, 0]]
    rec["rot"] = [[255, 128, 128, 128]] * 3  # identity (w = 127/128)
    p = tmp_path / "s.splat"
    rec.tofile(p)
    s = load_scene(p, SceneOptions(min_opacity=0.4))
    assert s.stats.read == 3 and s.stats.filtered_opacity == 1
    # the 8-bit quaternion is decoded at its bucket's centre (within ~0.6 deg of identity here) and the
    # sphere is inflated by the bucket's rotation bound (tests/scene/test_quantized.py)
    np.testing.assert_allclose(s.ellipsoids.rotations[0], np.eye(3), atol=0.01)
    assert np.all(s.ellipsoids.sigmas >= 0.01 * (1 - 1e-7)) and np.all(s.ellipsoids.sigmas < 0.0105)
    assert s.stats.quantized_inflated == 3


def test_the_scene_hash_is_the_files_sha256_and_its_thread_stops_on_an_error(tmp_path):
    """load_scene hashes the file on a thread while it parses (1.2 s of the 6M-splat room's read): the same
    digest as hashlib over the whole file, and after a refusal the thread is told to stop and ends."""
    import hashlib
    import threading

    cols = gaussian_columns(40, seed=5)
    p = write_ply(tmp_path / "g.ply", cols)
    assert load_scene(p).sha256 == hashlib.sha256(p.read_bytes()).hexdigest()
    cols["x"][3] = np.nan
    bad = write_ply(tmp_path / "bad.ply", cols)
    from polycc.errors import PolyccError

    with pytest.raises(PolyccError, match="NaN"):
        load_scene(bad)
    for t in threading.enumerate():
        if t.name == "polycc-sha256":
            t.join(5.0)
            assert not t.is_alive()


def test_row_chunks_on_threads_read_the_same_bits_as_one_pass(tmp_path, monkeypatch):
    """Regression for the chunked read (columns, activations, validity, rotations and AABB half-widths in row
    chunks on threads): the same bits as one chunk on one thread, with invalid splats dropped between chunks."""
    import polycc.parallel as par

    cols = gaussian_columns(3001, seed=7)
    cols["f_dc_0"], cols["f_dc_1"], cols["f_dc_2"] = (np.random.default_rng(1).normal(0, 1, 3001) for _ in range(3))
    cols["x"][[5, 700, 2999]] = np.nan  # invalid rows in several chunks
    cols["rot_0"][1200] = cols["rot_1"][1200] = cols["rot_2"][1200] = cols["rot_3"][1200] = 0.0
    cols["opacity"][[3, 2500]] = [80.0, -800.0]  # sigmoid saturates (exp overflows: no warning, no NaN)
    p = write_ply(tmp_path / "g.ply", cols)

    def read():
        s = load_scene(p, SceneOptions(drop_invalid=True, min_opacity=0.01))
        e = s.ellipsoids
        return s.stats.as_dict(), [np.ascontiguousarray(a).view(np.uint8) for a in
                                   (e.centers, e.rotations, e.sigmas, e.opacity, e.colors, e.aabb_halfwidth())]

    monkeypatch.setattr(par, "ROW_CHUNK", 1 << 30)
    monkeypatch.setattr(par, "available_cores", lambda: 1)
    one_stats, one = read()
    monkeypatch.setattr(par, "ROW_CHUNK", 97)
    monkeypatch.setattr(par, "available_cores", lambda: 3)
    many_stats, many = read()
    assert one_stats == many_stats and one_stats["invalid"] == 4 and one_stats["filtered_opacity"] >= 1
    assert all(np.array_equal(a, b) for a, b in zip(one, many))
