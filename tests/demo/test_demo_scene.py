"""The synthetic flight arena and `polycc demo-scene`."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData
from scipy.spatial import cKDTree

from polycc.cli import main
from polycc.demo.arena import ARENA_FORMAT, build_demo_arena, demo_arena_description, make_demo_arena


@pytest.fixture(scope="module")
def arena():
    return build_demo_arena(0)


def test_size_and_splat_shapes(arena):
    ell, _ = arena
    assert 150_000 <= len(ell) <= 300_000
    assert ell.k == 1.0
    assert ell.centers.dtype == np.float64 and ell.centers.shape == (len(ell), 3)
    # Flat discs: two tangent sigmas of mm..2 cm, one normal sigma of 1-2 mm.
    assert np.all(ell.sigmas[:, :2] >= 0.002 - 1e-12) and np.all(ell.sigmas[:, :2] <= 0.02 + 1e-12)
    assert np.all(ell.sigmas[:, 2] >= 0.001 - 1e-12) and np.all(ell.sigmas[:, 2] <= 0.002 + 1e-12)
    R = ell.rotations[::97]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert ell.opacity.dtype == np.float32 and np.all((ell.opacity > 0) & (ell.opacity <= 1))
    assert ell.colors.dtype == np.uint8 and ell.colors.shape == (len(ell), 3)


def test_room_bounds(arena):
    ell, desc = arena
    lo, hi = ell.bounds()
    assert np.all(lo[:2] > -3.1) and np.all(hi[:2] < 3.1) and np.all(hi[:2] - lo[:2] > 5.9)
    assert -0.05 < lo[2] < 0.0 and 2.0 < hi[2] <= 3.0
    assert desc["room"] == {"min": [-3.0, -3.0, 0.0], "max": [3.0, 3.0, 3.0]}
    assert desc["n_splats"] == len(ell)


def test_deterministic():
    a, b, c = make_demo_arena(7), make_demo_arena(7), make_demo_arena(8)
    for name in ("centers", "rotations", "sigmas", "opacity", "colors"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.centers[:100], c.centers[:100])
    assert demo_arena_description(7) == demo_arena_description(8) | {"seed": 7}


def test_description_format(arena):
    _, desc = arena
    assert desc["format"] == ARENA_FORMAT and desc["units"] == "m"
    assert 2 <= len(desc["hoops"]) <= 3
    assert len(desc["poles"]) >= 2 and len(desc["boxes"]) >= 2
    for h in desc["hoops"]:
        assert 0.35 <= h["radius"] <= 0.5
        assert 0.03 <= h["tube_radius"] <= 0.05
        assert h["radius"] == pytest.approx(h["major_radius"] - h["tube_radius"])
        assert np.linalg.norm(h["normal"]) == pytest.approx(1.0)
        assert abs(h["normal"][2]) < 1e-9  # upright
    heights = {h["center"][2] for h in desc["hoops"]}
    assert len(heights) == len(desc["hoops"])  # at various heights
    assert len(desc["flights"]) == len(desc["hoops"])
    assert desc["start"] == desc["flights"][0]["start"] and desc["goal"] == desc["flights"][0]["goal"]
    json.dumps(desc)  # JSON-ready


def test_hoops_are_there_and_open(arena):
    ell, desc = arena
    tree = cKDTree(ell.centers)
    for h in desc["hoops"]:
        c, n = np.array(h["center"]), np.array(h["normal"])
        # Free space through the centre.
        assert not tree.query_ball_point(c, 0.25)
        # The tube is there: splats on the torus surface, all round the ring.
        d = ell.centers - c
        axial = d @ n
        radial = np.linalg.norm(d - axial[:, None] * n, axis=1)
        on_tube = np.hypot(radial - h["major_radius"], axial) < h["tube_radius"] + 0.005
        assert on_tube.sum() > 5000
        B = np.linalg.svd(np.eye(3) - np.outer(n, n))[0][:, :2]  # two in-plane axes
        ang = np.arctan2(d[on_tube] @ B[:, 1], d[on_tube] @ B[:, 0])
        assert np.histogram(ang, bins=36, range=(-np.pi, np.pi))[0].min() > 50


def test_flights_are_clear(arena):
    """Each suggested flight is a straight line through its hoop, 0.3 m clear of every splat."""
    ell, desc = arena
    tree = cKDTree(ell.centers)
    room_lo, room_hi = np.array(desc["room"]["min"]), np.array(desc["room"]["max"])
    for f in desc["flights"]:
        s, g = np.array(f["start"]), np.array(f["goal"])
        assert np.all(s > room_lo + 0.3) and np.all(s < room_hi - 0.3)
        assert np.all(g > room_lo + 0.3) and np.all(g < room_hi - 0.3)
        hoop = desc["hoops"][f["hoop"]]
        mid = 0.5 * (s + g)
        np.testing.assert_allclose(mid, hoop["center"], atol=1e-6)
        np.testing.assert_allclose((g - s) / np.linalg.norm(g - s), hoop["normal"], atol=1e-6)
        line = s + np.linspace(0.0, 1.0, 400)[:, None] * (g - s)
        dist, _ = tree.query(line)
        assert dist.min() > 0.3


def test_cli_writes_ply_and_json(tmp_path, capsys):
    out = tmp_path / "sub" / "arena.ply"
    assert main(["demo-scene", str(out), "--seed", "3"]) == 0
    ply = PlyData.read(str(out))
    v = ply["vertex"]
    assert len(v.properties) == 62 and not ply.text
    desc = json.loads(out.with_suffix(".json").read_text())
    ell = make_demo_arena(3)
    assert v.count == len(ell) == desc["n_splats"]
    assert desc == json.loads(json.dumps(demo_arena_description(3, ell)))
    np.testing.assert_allclose(v["x"][:1000], ell.centers[:1000, 0], atol=1e-6)
    printed = capsys.readouterr().out
    assert "splats" in printed and "hoop_0" in printed


def test_cli_loads_through_scene_loader(tmp_path):
    scene = pytest.importorskip("polycc.scene.load")
    out = tmp_path / "arena.ply"
    assert main(["demo-scene", str(out)]) == 0
    got = scene.load_scene(out, scene.SceneOptions()).ellipsoids
    ell = make_demo_arena(0)
    assert len(got) == len(ell)
    np.testing.assert_allclose(got.centers, ell.centers, atol=1e-5)
    np.testing.assert_allclose(got.sigmas, ell.sigmas, rtol=1e-5)
    np.testing.assert_allclose(got.opacity, ell.opacity, atol=1e-6)


def test_cli_help_and_errors(tmp_path, capsys):
    assert main(["demo-scene", "--help"]) == 0  # main returns the exit code, also for --help
    text = capsys.readouterr().out
    for word in ("OUT.ply", "--seed", "--ascii", "metres", " m ", "default"):
        assert word in text
    assert main(["demo-scene", str(tmp_path / "arena.txt")]) == 2
    assert "must be a .ply" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert main(["demo-scene", str(tmp_path / "file" / "arena.ply")]) == 2


@pytest.mark.slow
def test_cli_ascii(tmp_path):
    out = tmp_path / "arena.ply"
    assert main(["demo-scene", str(out), "--ascii"]) == 0
    ell = make_demo_arena(0)
    with open(out) as f:
        header = [next(f).strip() for _ in range(66)]
        rows = np.loadtxt(f, max_rows=2000, dtype=np.float32)
    assert header[:3] == ["ply", "format ascii 1.0", f"element vertex {len(ell)}"]
    assert header[-1] == "end_header" and len(header[3:-1]) == 62
    np.testing.assert_allclose(rows[:, :3], ell.centers[:2000], atol=1e-6)
    np.testing.assert_allclose(np.exp(rows[:, 55:58]), ell.sigmas[:2000], rtol=1e-5)
