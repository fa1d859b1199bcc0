"""`polycc cover` then `polycc verify` on every real scene, the capture arena and the demo arena (slow)."""

from __future__ import annotations

import numpy as np
import pytest

from polycc.cli import main
from polycc.scene.writers import write_gaussian_ply
from polycc.testing.files import SCENES  # noqa: E402

SCENE_FILES = sorted(p.name for p in SCENES.glob("*") if p.suffix in (".ply", ".splat")) if SCENES.is_dir() else []


def cover_and_verify(ply, out, capsys, levels: str = "150,50,10") -> str:
    """cover, then verify: (a) at every level by certificate, (a)-(c) directly at ``levels``."""
    assert main(["cover", str(ply), "-o", str(out), "--voxel", "0.05", "--plot-n", "10,50",
                 "--mc-samples", "5000"]) == 0
    for f in ("cover.npz", "cover.json", "tradeoff.png", "cover_n10.png"):
        assert (out / f).is_file()
    capsys.readouterr()
    fam_n = int(np.load(out / "cover.npz")["leaf_voxel"].shape[0])
    lv = ",".join(x for x in levels.split(",") if x == "default" or int(x) <= fam_n) or "1"
    rc = main(["verify", str(out), str(ply), "--voxel", "0.05", "--mc-samples", "50000", "--levels", lv])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert rc == 0, last
    assert last.startswith("verify: PASS") and "uncovered voxels 0 points 0" in last
    return last


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENE_FILES)
def test_real_scene(name, scenes_dir, tmp_path, capsys):
    from polycc.demo.arenas import load_capture

    ply = tmp_path / "scene.ply"
    write_gaussian_ply(ply, load_capture(scenes_dir / name, 1.0))  # ~1 m across, z up, metres
    cover_and_verify(ply, tmp_path / "out", capsys)


@pytest.mark.slow
def test_capture_arena(scenes_dir, tmp_path, capsys):
    from polycc.demo.arenas import capture_arena

    ply = tmp_path / "arena.ply"
    write_gaussian_ply(ply, capture_arena(scenes_dir))
    cover_and_verify(ply, tmp_path / "out", capsys)


@pytest.mark.slow
def test_demo_arena(tmp_path, capsys):
    ply = tmp_path / "demo.ply"
    assert main(["demo-scene", str(ply)]) == 0
    cover_and_verify(ply, tmp_path / "out", capsys, levels="default")


@pytest.mark.slow
def test_random_scenes(tmp_path, capsys):
    from polycc.scene.ellipsoids import Ellipsoids, quaternion_to_rotation

    for seed in range(3):
        rng = np.random.default_rng(seed)
        n = 800
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1)[:, None]
        ell = Ellipsoids(rng.uniform(-1, 1, (n, 3)), quaternion_to_rotation(q), np.exp(rng.uniform(-6, -2.5, (n, 3))),
                         1.0, opacity=np.full(n, 0.9, np.float32))
        ply = tmp_path / f"r{seed}.ply"
        write_gaussian_ply(ply, ell)
        cover_and_verify(ply, tmp_path / f"out{seed}", capsys)
