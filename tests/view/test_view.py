"""polycc export (trimesh meshes of the stored polytopes) and polycc view (viser page in a real headless Chromium)."""

from __future__ import annotations

import io
import json
import os
import time

import numpy as np
import pytest

from polycc.cli import main
from polycc.testing.browser import chromium_path


@pytest.fixture(scope="module")
def build_dir(tmp_path_factory):
    from polycc.testing.files import SCENES

    if not SCENES.is_dir():
        pytest.skip(f"real scenes not found at {SCENES}")
    d = tmp_path_factory.mktemp("view")
    assert main(["build", str(SCENES / "donut_fused.ply"), "--scale", "4", "--flash-kb", "8", "--mc-samples", "2000",
                 "-o", str(d / "b")]) == 0
    return d / "b"


def test_export_formats_and_frames(build_dir, tmp_path):
    import trimesh

    man = json.loads((build_dir / "manifest.json").read_text())
    n = len(man["polytopes"])
    for fmt in ("glb", "obj", "ply"):
        out = tmp_path / f"c.{fmt}"
        assert main(["export", str(build_dir), "-o", str(out)] + (["--frame", "trainer"] if fmt == "obj" else [])) == 0
        m = trimesh.load(out, force="mesh")
        assert len(m.faces) >= 4 * n
    # every exported vertex satisfies its polytope's half-planes (world frame)
    from polycc.view.meshes import polytope_meshes

    meshes = polytope_meshes(man, "world")
    assert len(meshes) == n
    for p, m in zip(man["polytopes"], meshes):
        h = np.asarray(p["halfplanes"])
        assert np.all(m.vertices @ h[:, :3].T <= h[:, 3] + 1e-6)
    # trainer frame = inverse of the build's file -> world matrix
    T = np.asarray(man["scene_settings"]["world_matrix"])
    tr = polytope_meshes(man, "trainer")
    back = tr[0].vertices @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(np.sort(back, axis=0), np.sort(meshes[0].vertices, axis=0), atol=1e-9)


def test_export_errors_are_one_line(tmp_path, capsys):
    assert main(["export", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "polycc build" in err


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _png(data: bytes) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(io.BytesIO(data), format="png")[..., :3]


@pytest.mark.slow
def test_view_page_draws_the_scene_in_chromium(build_dir, tmp_path):
    """The page loads in a real headless Chromium, connects, shows the build summary and draws the scene: the
    screenshot is not blank and holds the cover's colours (tab20, one per polytope) where the scene is."""
    if chromium_path() is None:
        if os.environ.get("CI"):
            pytest.fail("CI must install Debian's chromium (see .ci/run)")
        pytest.skip("chromium not installed (apt-get install chromium)")
    pytest.importorskip("playwright")
    from polycc.scene.load import load_scene
    from polycc.scene.settings import recorded_settings
    from polycc.testing.browser import Page
    from polycc.view.viewer import content_for, start

    # a flight, as `polycc sim` writes it
    np.savez_compressed(build_dir / "trajectories.npz", trial1=np.linspace([0, -0.5, 0.3], [0, 0.5, 0.3], 50),
                        starts=np.array([[0, -0.5, 0.3]]), goals=np.array([[0, 0.5, 0.3]]))
    settings, rec = recorded_settings(build_dir)
    scene = load_scene(rec["path"], settings.scene_options())
    content = content_for(build_dir, scene.ellipsoids)
    assert len(content.flights) == 1
    server = start(content, "127.0.0.1", _free_port(), max_splats=5000)
    try:
        with Page(f"http://127.0.0.1:{server.get_port()}", width=800, height=500) as page:
            page.wait_for_text_gone("Connecting", 90)
            # regression (CI): read at once after "Connected", the side panel had not arrived yet
            page.wait_for_text("chosen n", "flights", timeout_s=90)
            time.sleep(10)  # let the splats and meshes arrive and fade in (software WebGL is slow)
            png = page.png()
    finally:
        server.stop()
    (tmp_path / "view.png").write_bytes(png)
    img = _png(png)
    view = img[150:480, 60:400]  # the 3D view, below the notice, left of the side panel, right of the axes
    assert img.std() > 0.02, "the page is blank"
    sat = view.max(axis=2) - view.min(axis=2)  # background and grid are grey (0); the cover is tab20 colours
    assert (sat > 0.04).mean() > 0.005, "no coloured (cover) pixels where the scene is"
