"""`polycc verify` on `polycc build` output: the decoded stored polytopes must cover the scene."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polycc.cli import main
from polycc.scene.load import load_scene
from polycc.testing.files import SCENES

SCENE_FILES = sorted(p.name for p in SCENES.glob("*")) if SCENES.is_dir() else []
SCENE_FILES = [f for f in SCENE_FILES if f.endswith((".ply", ".splat"))]


def metric_scale(name: str) -> float:
    """Scale that makes the scene's longest side (0.5-99.5 percentile of centres) 1 m."""
    c = load_scene(SCENES / name).ellipsoids.centers
    ext = np.percentile(c, 99.5, axis=0) - np.percentile(c, 0.5, axis=0)
    return float(f"{1.0 / ext.max():.6g}")


def build_and_verify(tmp_path, name, kb, capsys, voxel="0.03"):
    scale = metric_scale(name)
    out = tmp_path / f"{name}-{kb}"
    common = ["--scale", str(scale), "--voxel", voxel]
    assert main(["build", str(SCENES / name), "--flash-kb", str(kb), "--mc-samples", "20000", "-o", str(out),
                 *common]) == 0
    capsys.readouterr()
    rc = main(["verify", str(out), str(SCENES / name), "--min-samples", "200000", "--mc-samples", "20000", *common])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    return rc, last, out


def test_verify_passes_on_build_output(tmp_path, scenes_dir, capsys):
    rc, last, _ = build_and_verify(tmp_path, "ring_10k.splat", 4, capsys)
    assert rc == 0 and last.startswith("verify: PASS") and "uncovered voxels 0 points 0" in last


def test_verify_fails_when_a_stored_polytope_shrinks(tmp_path, scenes_dir, capsys):
    _, _, out = build_and_verify(tmp_path, "ring_10k.splat", 4, capsys)
    man = json.loads((out / "manifest.json").read_text())
    h = np.asarray(man["polytopes"][0]["halfplanes"])
    h[:, 3] -= 0.004  # shrink one polytope by 4 mm
    man["polytopes"][0]["halfplanes"] = h.tolist()
    (out / "manifest.json").write_text(json.dumps(man))
    scale = metric_scale("ring_10k.splat")
    rc = main(["verify", str(out), str(SCENES / "ring_10k.splat"), "--scale", str(scale), "--voxel", "0.03",
               "--min-samples", "200000", "--mc-samples", "2000"])
    assert rc == 1 and "verify: FAIL" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.parametrize("kb", [8, 16, 32, 64])
@pytest.mark.parametrize("name", SCENE_FILES)
def test_verify_every_real_scene_at_every_budget(tmp_path, scenes_dir, capsys, name, kb):
    rc, last, out = build_and_verify(tmp_path, name, kb, capsys)
    assert rc == 0, last
    assert json.loads((out / "manifest.json").read_text())["stats"]["bytes"] <= kb * 1024
