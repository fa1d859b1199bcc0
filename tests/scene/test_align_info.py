"""polycc info and polycc align: a y-down, non-metric capture goes to a gravity-aligned, floor-at-z=0 frame in
metres in one `polycc align`; transforms accept nerfstudio's dataparser_transforms.json and 3x4 matrices; the
size check runs before heavy work; progress shows when piped."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polycc.cli import main
from polycc.demo.arena import build_demo_arena
from polycc.errors import PolyccError
from polycc.scene.load import SceneOptions, load_scene
from polycc.scene.transform import apply_transform, load_transform
from polycc.scene.writers import write_gaussian_ply

# a y-down capture: world +z is the file's -y; and 37 file units per metre, offset
Y_DOWN = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # file = Y_DOWN @ world


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    ell, desc = build_demo_arena(seed=3)
    T = np.eye(4)
    T[:3, :3] = 37.0 * Y_DOWN
    T[:3, 3] = [5.0, -2.0, 11.0]
    path = tmp_path_factory.mktemp("cap") / "capture.ply"
    write_gaussian_ply(path, apply_transform(ell, T))
    return path, ell, T


def test_align_undoes_y_down_and_scale(capture, tmp_path, capsys):
    path, world, T = capture
    lo, hi = np.percentile(world.centers, [0.5, 99.5], axis=0)
    longest = float(np.max(hi - lo))
    out = tmp_path / "t.json"
    assert main(["align", str(path), "--size", f"{longest:.9g}", "-o", str(out)]) == 0
    M = load_transform(out)
    A = M[:3, :3] @ T[:3, :3]  # world -> file -> aligned: a rotation about z (yaw is free) at scale 1
    s = np.cbrt(np.linalg.det(A))
    assert abs(s - 1.0) < 0.01
    np.testing.assert_allclose(A[2] / s, [0, 0, 1], atol=0.02)  # up is +z again
    aligned = load_scene(path, SceneOptions(transform=M)).ellipsoids
    floor = aligned.centers[np.abs(world.centers[:, 2]) < 0.02]  # the arena's floor splats
    assert abs(float(np.median(floor[:, 2]))) < 0.02  # floor at z = 0
    rec = json.loads(out.read_text())["polycc_align"]
    assert rec["floor_method"].startswith("RANSAC")


def test_align_with_explicit_up_and_known_distance(capture, tmp_path):
    path, world, T = capture
    p1, p2 = T[:3, :3] @ [0, 0, 0] + T[:3, 3], T[:3, :3] @ [2.0, 0, 0] + T[:3, 3]  # 2 m apart in the world
    out = tmp_path / "k.json"
    args = ["align", str(path), "--up", "-y", "--known-distance", ",".join(f"{v:.9g}" for v in [*p1, *p2, 2.0]),
            "-o", str(out)]
    assert main(args) == 0
    M = load_transform(out)
    s = np.cbrt(np.linalg.det(M[:3, :3] @ T[:3, :3]))
    assert abs(s - 1.0) < 1e-6


def test_info_reports_up_axis_extent_and_warns(capture, capsys):
    path, _, _ = capture
    assert main(["info", str(path), "--no-timing"]) == 0
    out, err = capsys.readouterr()
    assert "up -y" in out  # the capture is y-down
    assert "not metres" in err and "polycc align" in err  # 37 units per metre: extent ~ 200 units


def test_info_lists_far_isolated_splats(tmp_path, capsys):
    ell, _ = build_demo_arena(seed=1)
    far = ell.subset(np.arange(5))
    far.centers = far.centers + np.array([30.0, 0, 0])  # five floaters 30 m away
    from polycc.scene.ellipsoids import Ellipsoids

    p = tmp_path / "f.ply"
    write_gaussian_ply(p, Ellipsoids.concatenate([ell, far]))
    assert main(["info", str(p), "--no-timing", "--group-radius", "0.2"]) == 0
    out = capsys.readouterr().out
    assert "outlier groups" in out and "5 splats in small groups" in out


def test_drop_isolated_drops_and_lists_them(tmp_path):
    ell, _ = build_demo_arena(seed=1)
    far = ell.subset(np.arange(5))
    far.centers = far.centers + np.array([30.0, 0, 0])
    from polycc.scene.ellipsoids import Ellipsoids

    p = tmp_path / "f.ply"
    write_gaussian_ply(p, Ellipsoids.concatenate([ell, far]))
    s = load_scene(p, SceneOptions(drop_isolated=(0.2, 20)))
    assert s.stats.dropped_isolated == 5 and s.stats.kept == len(ell)
    assert len(s.dropped_groups) >= 1 and s.dropped_groups[0].gap > 25


def test_nerfstudio_dataparser_transforms_and_3x4(tmp_path):
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=1).as_matrix()
    fwd = np.hstack([R, [[0.3], [-1.0], [2.0]]])
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": fwd.tolist(), "scale": 0.25}))
    T = load_transform(tmp_path / "dataparser_transforms.json")
    p = rng.normal(size=(10, 3))
    p_ns = 0.25 * (p @ R.T + fwd[:, 3])  # nerfstudio's frame
    np.testing.assert_allclose(p_ns @ T[:3, :3].T + T[:3, 3], p, atol=1e-12)  # back to the capture's frame
    (tmp_path / "m34.json").write_text(json.dumps({"matrix": fwd.tolist()}))
    np.testing.assert_allclose(load_transform(tmp_path / "m34.json")[:3], fwd)
    (tmp_path / "bare34.json").write_text(json.dumps(fwd.tolist()))
    np.testing.assert_allclose(load_transform(tmp_path / "bare34.json")[:3], fwd)
    (tmp_path / "bad.json").write_text(json.dumps({"matrix": [[1, 0], [0, 1]]}))
    with pytest.raises(PolyccError, match="3x4"):
        load_transform(tmp_path / "bad.json")


def test_wrong_scale_is_refused_before_voxelizing(capture, tmp_path, capsys):
    """A scene at the wrong scale (x100) ran 2 minutes with no warning: now one line, before the work."""
    path, _, _ = capture
    assert main(["voxelize", str(path), "--scale", "3.7", "-o", str(tmp_path / "o.npz")]) == 2
    err = capsys.readouterr().err
    assert "voxels" in err and "--voxel" in err and len(err.strip().splitlines()) <= 2


def test_progress_lines_when_piped(capture, tmp_path, capsys):
    path, _, _ = capture
    t = tmp_path / "t.json"
    assert main(["align", str(path), "--size", "6", "-o", str(t)]) == 0
    capsys.readouterr()
    assert main(["voxelize", str(path), "--transform", str(t), "-o", str(tmp_path / "o.npz")]) == 0
    out = capsys.readouterr().out
    assert "reading the scene..." in out and "voxelizing: 0/" in out and "(100 %)" in out


def test_verify_help_says_95_percent(capsys):
    with pytest.raises(SystemExit):
        from polycc.cli import build_parser

        build_parser().parse_args(["verify", "--help"])
    out = capsys.readouterr().out
    assert "95 %" in out and "%%" not in out


def test_tables_fit_80_columns(capture, tmp_path, capsys):
    path, _, _ = capture
    assert main(["info", str(path), "--no-timing"]) == 0
    out = capsys.readouterr().out
    # every table line fits; the closing one-line result ("info: ...") is one line by design, for grep
    assert max(len(line) for line in out.splitlines() if not line.startswith("info:")) <= 80
