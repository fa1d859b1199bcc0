"""Regression tests: places where polycc reported safety that was not there .

1. sim/verify/sim-device take the scene settings from the build folder; a disagreeing option is an error.
2. A mesh .ply (face element) was read as its corner points: now its triangles are voxelized exactly.
3. A .ply body longer or shorter than its header is refused (binary and ASCII).
4. The floater filter reports the voxels it removed, the splats it leaves partly uncovered and how deep.
5. Bad option values are one-line errors with exit code 2.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from polycc.cli import main
from polycc.errors import PolyccError
from polycc.occupancy.exact import voxelize
from polycc.occupancy.floaters import floater_loss
from polycc.scene.load import SceneOptions, load_scene
from polycc.scene.readers import read_splats
from polycc.testing.files import gaussian_columns, write_ply


# ---------------------------------------------------------------------------- 1. scene settings
def _trainer_frame_scene(path):
    """A slab of splats in a y-down, half-scale trainer frame (metres after the transform below)."""
    rng = np.random.default_rng(4)
    n = 600
    # world: a wall x in [0.9, 1.1], y in [-0.5, 0.5], z in [0.3, 1.3]; trainer p_t = R^T (p_w - t) / s
    pw = np.c_[rng.uniform(0.9, 1.1, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.3, 1.3, n)]
    s, t = 2.0, np.array([0.0, 0.0, 0.5])
    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # trainer y-down, z-back -> world z-up
    pt = (pw - t) @ R / s
    cols = {"x": pt[:, 0], "y": pt[:, 1], "z": pt[:, 2], "opacity": np.full(n, 3.0)}
    for i in range(3):
        cols[f"scale_{i}"] = np.full(n, np.log(0.01 / s))  # 1 cm in world units
    for i, v in enumerate((1.0, 0.0, 0.0, 0.0)):
        cols[f"rot_{i}"] = np.full(n, v)
    write_ply(path, cols)
    tf = path.with_name("tf.json")
    tf.write_text(json.dumps({"scale": s, "rotation": R.tolist(), "translation": t.tolist()}))
    return path, tf


@pytest.fixture(scope="module")
def transformed_build(tmp_path_factory):
    d = tmp_path_factory.mktemp("tf")
    scene, tf = _trainer_frame_scene(d / "wall.ply")
    out = d / "b"
    assert main(["build", str(scene), "--transform", str(tf), "--sigma", "3", "--flash-kb", "4",
                 "--mc-samples", "2000", "-o", str(out)]) == 0
    return scene, tf, out


def _exact_clearance(positions, ell, radius):
    from polycc.sim.clearance import densify, point_ellipsoid_distance

    P = densify(positions)
    best = np.inf
    a = ell.sigmas * ell.k
    for s in range(0, len(P), 200):
        p = P[s : s + 200]
        y = np.einsum("nji,pnj->pni", ell.rotations, p[:, None, :] - ell.centers[None])
        d = point_ellipsoid_distance(y.reshape(-1, 3), np.tile(a, (len(p), 1)))
        best = min(best, float(d.min()))
    return best - radius


def test_sim_uses_the_builds_transform_and_sigma(transformed_build, capsys):
    """A transformed sigma = 3 scene flown without repeating the options: the reported clearance
    is the exact one in the build's frame (it was 60x optimistic without the transform)."""
    scene, tf, out = transformed_build
    rc = main(["sim", str(out), "--start", "0.5,-0.9,0.8", "--goal", "1.5,-0.9,0.8", "--t-max", "8"])
    assert rc in (0, 1)
    rep = json.loads((out / "sim.json").read_text())
    P = np.load(out / "trajectories.npz")["trial1"]
    from polycc.scene.transform import load_transform

    truth = load_scene(scene, SceneOptions(sigma=3.0, transform=load_transform(tf))).ellipsoids
    exact = _exact_clearance(P, truth, rep["radius"])
    assert abs(rep["min_clearance_m"] - exact) < 1e-6, (rep["min_clearance_m"], exact)
    # and it is not the clearance to the untransformed scene
    wrong = _exact_clearance(P, load_scene(scene, SceneOptions(sigma=3.0)).ellipsoids, rep["radius"])
    assert abs(wrong - exact) > 0.05


@pytest.mark.parametrize("opts, needle", [
    (["--sigma", "1"], "--sigma 1 disagrees"),
    (["--scale", "2"], "--scale 2 gives the file->world matrix"),
    (["--voxel", "0.02"], "--voxel 0.02 disagrees"),
])
def test_explicit_option_that_disagrees_with_the_build_is_an_error(transformed_build, capsys, opts, needle):
    scene, tf, out = transformed_build
    for cmd in (["sim", str(out), "--start", "0.5,-0.9,0.8", "--goal", "1.5,-0.9,0.8"],
                ["verify", str(out), str(scene)]):
        assert main(cmd + opts) == 2
        err = capsys.readouterr().err.strip()
        assert needle in err and len(err.splitlines()) == 1, err
        assert "built with" in err


def test_verify_takes_the_builds_settings(transformed_build, capsys):
    scene, tf, out = transformed_build
    assert main(["verify", str(out), str(scene), "--min-samples", "20000", "--mc-samples", "2000"]) == 0
    text = capsys.readouterr().out
    assert "verify: PASS against the exact occupancy" in text


def test_another_scene_than_the_build_is_an_error(transformed_build, tmp_path, capsys):
    scene, tf, out = transformed_build
    other = write_ply(tmp_path / "other.ply", gaussian_columns(30))
    assert main(["sim", str(out), "--scene", str(other), "--start", "0,0,1", "--goal", "1,0,1"]) == 2
    assert "is not the scene" in capsys.readouterr().err
    assert main(["sim-device", str(out), "--scene", str(other), "--udp", "127.0.0.1:0", "--duration", "0.1"]) == 2
    assert "is not the scene" in capsys.readouterr().err


# ---------------------------------------------------------------------------- 2., 3. ply bodies
def test_mesh_ply_triangles_are_voxelized(tmp_path, capsys):
    """A 4 x 3 m wall as two triangles was read as its 4 corner points (then refused); now every voxel its
    surface meets is occupied (its plane and edges lie on voxel faces, so both layers of closed voxels meet them:
    x in -1..8, z in -1..6, y in -1..0)."""
    from polycc.occupancy.grid import OccupancyGrid

    v = np.array([(0, 0, 0), (4, 0, 0), (4, 0, 3), (0, 0, 3)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    f = np.array([([0, 1, 2],), ([0, 2, 3],)], dtype=[("vertex_indices", "i4", (3,))])
    p = tmp_path / "wall.ply"
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")]).write(str(p))
    assert read_splats(p).triangles.shape == (2, 3, 3)
    assert main(["voxelize", str(p), "--voxel", "0.5", "-o", str(tmp_path / "o.npz")]) == 0
    g = OccupancyGrid.load(tmp_path / "o.npz")
    assert len(g) == 10 * 8 * 2 and set(g.indices[:, 1]) == {-1, 0}


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("delta", [+1, -1])
def test_ply_body_must_match_its_header(tmp_path, text, delta):
    """A header declaring 39 vertices over a body of 40 built with exit 0; the 40th splat lay outside."""
    cols = gaussian_columns(40, seed=2)
    full = write_ply(tmp_path / "full.ply", cols, text=text)
    short = {k: v[:39] for k, v in cols.items()}
    ref = write_ply(tmp_path / "ref.ply", short, text=text)
    head_len = ref.read_bytes().index(b"end_header") + len(b"end_header\n")
    if delta > 0:  # the 39-vertex header over the 40-vertex body
        body = full.read_bytes()[full.read_bytes().index(b"end_header") + len(b"end_header\n"):]
    else:  # the 39-vertex header over a 38-vertex body
        body = ref.read_bytes()[head_len:]
        body = body[: body.rstrip(b"\n").rfind(b"\n") + 1] if text else body[: -len(body) // 39]
    bad = tmp_path / "bad.ply"
    bad.write_bytes(ref.read_bytes()[:head_len] + body)
    with pytest.raises(PolyccError):
        read_splats(bad)
    read_splats(ref)  # the consistent file reads


# ---------------------------------------------------------------------------- 4. floater filter
def _floater_scene():
    return gaussian_columns(400, seed=11, scale_log=(-4.0, -2.5))


def test_floater_loss_is_a_certified_bound(tmp_path):
    """The reported depth bounds the distance of sampled ellipsoid points from the kept voxels,
    and the count matches a brute-force check."""
    p = write_ply(tmp_path / "f.ply", _floater_scene())
    ell = load_scene(p, SceneOptions(sigma=2.0)).ellipsoids
    g = 0.05
    occ = voxelize(ell, g, 3)
    loss = floater_loss(ell, occ.indices, occ.removed, g, occ.origin, tol_m=5e-4)
    assert loss["voxels_removed"] == len(occ.removed) > 0
    assert loss["splats_not_fully_covered"] > 0
    # brute force: points in every ellipsoid, distance to the kept voxels
    from polycc.occupancy.floaters import _DistanceToVoxels
    from polycc.verify.certify import sample_ellipsoids

    pts = sample_ellipsoids(ell.centers, ell.axes(), 400, np.random.default_rng(0)).reshape(len(ell), 400, 3)
    dist = _DistanceToVoxels(occ.lower_corners(), g)
    d = dist(pts.reshape(-1, 3)).reshape(len(ell), 400)
    outside = d.max(axis=1) > 0
    assert d.max() <= loss["max_depth_outside_m"] + 1e-12
    assert loss["max_depth_outside_m"] - loss["depth_lower_m"] <= 5e-4 + 1e-12
    # every splat with a sampled point outside the kept voxels is counted
    assert set(np.flatnonzero(outside)) <= set(loss["splats"].tolist())


def test_build_reports_the_floater_filter(tmp_path, capsys):
    p = write_ply(tmp_path / "f.ply", _floater_scene())
    out = tmp_path / "b"
    assert main(["build", str(p), "--min-splats-per-voxel", "3", "--flash-kb", "4", "--mc-samples", "2000",
                 "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "floater filter" in text and "NOT" in text
    man = json.loads((out / "manifest.json").read_text())
    # The app's loop rate for this header (issue 14: `polycc build` prints it).
    assert "on-board loop rate (polycc.rate)" in text and man["stats"]["app_rate_hz"] == 500
    f = man["stats"]["floater_filter"]
    assert f["voxels_removed"] > 0 and f["splats_not_fully_covered"] > 0 and f["max_depth_outside_m"] > 0
    header = (out / "polytopes.h").read_text()
    assert "Floaters:" in header and "NOT fully covered" in header
    assert main(["verify", str(out), str(p), "--min-samples", "20000", "--mc-samples", "2000"]) == 0
    vtext = capsys.readouterr().out
    assert "FILTERED occupancy" in vtext and "PASS" in vtext


# ---------------------------------------------------------------------------- 5. option values
@pytest.mark.parametrize("argv, needle", [
    (["build", "S", "--kappa", "0"], "--kappa"),
    (["build", "S", "--kappa", "0.5"], "[1, 10000]"),
    (["build", "S", "--kappa", "1e5"], "[1, 10000]"),
    (["build", "S", "--kappa", "nan"], "finite"),
    (["build", "S", "--kappa", "inf"], "finite"),
    (["build", "S", "--flash-kb", "inf"], "--flash-kb"),
    (["build", "S", "--cpu-share", "0"], "(0, 1]"),
    (["build", "S", "--cpu-share", "2"], "(0, 1]"),
    (["build", "S", "--mc-samples", "0"], "--mc-samples"),
    (["build", "S", "--rate-hz", "5"], "--rate-hz"),
    (["sim", "D", "--vmax", "-1"], "--vmax"),
    (["sim", "D", "--start", "1,2"], "--start"),
    (["voxelize", "S", "-o", "x.npz", "--voxel", "-0.1"], "--voxel"),
    (["voxelize", "S", "-o", "x.npz", "--sigma", "nan"], "--sigma"),
    (["verify", "D", "S", "--samples-per-ellipsoid", "3"], "--samples-per-ellipsoid"),
])
def test_bad_values_are_one_line_errors(capsys, argv, needle):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err


def test_output_that_is_a_file_is_an_error(tmp_path, capsys):
    p = write_ply(tmp_path / "s.ply", gaussian_columns(20))
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["build", str(p), "-o", str(f)]) == 2
    assert "is a file" in capsys.readouterr().err


def test_negative_coordinates_work(tmp_path, capsys):
    p = write_ply(tmp_path / "s.ply", gaussian_columns(50))
    out = tmp_path / "o.npz"
    assert main(["voxelize", str(p), "-o", str(out), "--crop", "-0.3,-1,-1,1,1,1"]) == 0
    from polycc.cli.argtypes import join_negative_values

    assert join_negative_values(["sim", "D", "--start", "-2,-2.5,1", "--goal", "-.5,0,1"]) == \
        ["sim", "D", "--start=-2,-2.5,1", "--goal=-.5,0,1"]
