"""``polycc view``: a browser view (viser) of a build's splats, stored cover and simulated flights.

World frame, metres, z up after ``polycc align``. The page shows

* the scene's splats as Gaussian splats (viser's renderer; at most ``max_splats``, a random subset beyond);
* the stored polytopes (manifest.json, the values the C decodes), one colour each, as one mesh;
* the chosen n, half-planes, bytes and conservativeness in the side panel;
* flights from ``polycc sim`` (``trajectories.npz``: ``trial1``, ``trial2``, ... true positions, ``starts``,
  ``goals``) as lines, with start (black) and goal (gold) markers.
Each layer has a checkbox.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.scene.ellipsoids import Ellipsoids
from polycc.view.meshes import polytope_meshes, read_build

MAX_SPLATS = 400_000


@dataclass
class ViewContent:
    manifest: dict
    ellipsoids: Ellipsoids | None
    flights: list = field(default_factory=list)  # (positions (n, 3), start, goal)
    notes: list = field(default_factory=list)


def read_flights(build_dir: Path) -> list:
    f = build_dir / "trajectories.npz"
    if not f.is_file():
        return []
    try:
        with np.load(f, allow_pickle=False) as z:
            keys = sorted((k for k in z.files if k.startswith("trial")), key=lambda k: int(k[5:] or 0))
            starts = z["starts"] if "starts" in z.files else None
            goals = z["goals"] if "goals" in z.files else None
            out = []
            for i, k in enumerate(keys):
                p = np.asarray(z[k], np.float64).reshape(-1, 3)
                s = starts[i] if starts is not None and i < len(starts) else p[0]
                g = goals[i] if goals is not None and i < len(goals) else p[-1]
                out.append((p, np.asarray(s, np.float64), np.asarray(g, np.float64)))
            return out
    except (OSError, ValueError, KeyError) as exc:
        raise PolyccError(f"{f}: not a readable trajectories file ({exc}); re-run `polycc sim`") from None


def summary_markdown(manifest: dict, n_splats: int | None, n_flights: int, notes: list) -> str:
    st = manifest.get("stats", {})
    lines = [f"**{manifest.get('scene', {}).get('name', 'scene')}**", "",
             f"- chosen n = **{st.get('n', len(manifest['polytopes']))}** polytopes, "
             f"{st.get('halfplanes', '?')} half-planes",
             f"- {st.get('bytes', '?')} of {st.get('budget_bytes', '?')} bytes",
             f"- conservativeness {st.get('conservativeness', float('nan')):.4f} "
             f"+- {st.get('conservativeness_ci95', float('nan')):.4f} (95 %)",
             f"- voxel {st.get('voxel_size_m', '?')} m, {st.get('voxels', '?')} voxels"]
    if n_splats is not None:
        lines.append(f"- {n_splats:,} splats shown")
    if n_flights:
        lines.append(f"- {n_flights} flights (green: path, black: start, gold: goal)")
    lines += [f"- {n}" for n in notes]
    return "\n".join(lines)


def splat_arrays(ell: Ellipsoids, max_splats: int = MAX_SPLATS, seed: int = 0):
    """(centres, covariances, rgb 0..1, opacity (N, 1)) for viser, at most ``max_splats`` (random subset)."""
    idx = np.arange(len(ell))
    if len(ell) > max_splats:
        idx = np.sort(np.random.default_rng(seed).choice(len(ell), max_splats, replace=False))
    e = ell.subset(idx)
    L = e.rotations * e.sigmas[:, None, :]
    cov = np.einsum("nij,nkj->nik", L, L)
    rgb = (e.colors / 255.0) if e.colors is not None else np.full((len(e), 3), 0.6)
    op = (np.asarray(e.opacity, np.float64) if e.opacity is not None else np.ones(len(e)))[:, None]
    return e.centers.astype(np.float32), cov.astype(np.float32), rgb.astype(np.float32), op.astype(np.float32)


def start(content: ViewContent, host: str = "127.0.0.1", port: int = 8080, max_splats: int = MAX_SPLATS):
    """Start the viser server with the content; returns the server (``server.stop()`` ends it) with
    ``server.polycc_layers``: the scene handles of each layer ("splats", "cover", "flights")."""
    import trimesh
    import viser

    server = viser.ViserServer(host=host, port=port, verbose=False)
    server.scene.set_up_direction("+z")
    server.gui.configure_theme(control_width="large")
    n_shown = None
    if content.ellipsoids is not None and len(content.ellipsoids) and max_splats > 0:
        c, cov, rgb, op = splat_arrays(content.ellipsoids, max_splats)
        n_shown = len(c)
        splats = server.scene.add_gaussian_splats("/splats", centers=c, covariances=cov, rgbs=rgb, opacities=op)
    else:
        splats = None
    meshes = polytope_meshes(content.manifest, "world")
    cover = []
    if meshes:  # one mesh per colour (tab20, polytope i gets colour i % 20), each one flat colour
        for k in range(min(20, len(meshes))):
            m = trimesh.util.concatenate(meshes[k::20])
            rgb = tuple(int(c) for c in np.asarray(m.visual.face_colors)[0, :3])
            cover.append(server.scene.add_mesh_simple(f"/cover/{k}", m.vertices, m.faces, color=rgb, opacity=0.85,
                                                      flat_shading=True, side="double"))
        allm = trimesh.util.concatenate(meshes)
        cover.append(server.scene.add_mesh_simple("/cover_edges", allm.vertices, allm.faces, wireframe=True,
                                                  color=(40, 40, 40), opacity=0.4))
    lines = []
    for i, (p, s, g) in enumerate(content.flights):
        if len(p) >= 2:
            seg = np.stack([p[:-1], p[1:]], axis=1).astype(np.float32)
            lines.append(server.scene.add_line_segments(f"/flights/{i}", seg, (40, 170, 60), thickness=4.0,
                                                         thickness_units="screen"))
        lines.append(server.scene.add_icosphere(f"/flights/{i}_start", radius=0.04, color=(10, 10, 10), position=s))
        lines.append(server.scene.add_icosphere(f"/flights/{i}_goal", radius=0.05, color=(230, 180, 20), position=g))
    server.scene.add_grid("/floor", width=10, height=10, cell_size=0.5, position=(0.0, 0.0, 0.0))
    server.gui.add_markdown(summary_markdown(content.manifest, n_shown, len(content.flights), content.notes))
    if splats is not None:
        cb = server.gui.add_checkbox("splats", True)
        cb.on_update(lambda _: setattr(splats, "visible", cb.value))
    if cover:
        cc = server.gui.add_checkbox("cover (stored polytopes)", True)

        def _cover(_):
            for h in cover:
                h.visible = cc.value

        cc.on_update(_cover)
    if lines:
        fc = server.gui.add_checkbox("flights", True)

        def _flights(_):
            for h in lines:
                h.visible = fc.value

        fc.on_update(_flights)
    _frame_camera(server, content)
    server.polycc_layers = {"splats": [splats] if splats is not None else [],
                            "cover": cover, "flights": lines}
    return server


def _frame_camera(server, content: ViewContent) -> None:
    if content.ellipsoids is not None and len(content.ellipsoids):
        lo = np.percentile(content.ellipsoids.centers, 1, axis=0)
        hi = np.percentile(content.ellipsoids.centers, 99, axis=0)
    else:
        lo, hi = np.full(3, -1.0), np.full(3, 1.0)
    mid = 0.5 * (lo + hi)
    r = max(float(np.linalg.norm(hi - lo)), 0.5)
    eye = mid + np.array([0.6, -0.8, 0.55]) * r

    @server.on_client_connect
    def _(client) -> None:
        client.camera.position = tuple(eye)
        client.camera.look_at = tuple(mid)
        client.camera.up_direction = (0.0, 0.0, 1.0)


def content_for(build_dir: str | Path, ellipsoids: Ellipsoids | None, notes: list | None = None) -> ViewContent:
    d = Path(build_dir)
    return ViewContent(read_build(d), ellipsoids, read_flights(d), list(notes or []))
