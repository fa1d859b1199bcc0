"""Scenes built from the real captures in ``../shared/scenes``, for benchmarks and tests.

All lengths are metres, z up, floor at z = 0. The captures are not metric and use
different up axes (:data:`CAPTURE_UP`); each is turned z-up and scaled so its longest
side is about 1 m (:func:`normalize_to_size`) before it is placed.

- :func:`capture_arena`: plant, ring and tree side by side on a 4 m x 4 m floor.
- :func:`tiled_room`: the ~1.5M-splat benchmark room, 10 m x 10 m x 3 m, tiled with
  randomly placed and turned copies of every capture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polycc.demo.arena import make_floor
from polycc.errors import PolyccError
from polycc.scene.ellipsoids import Ellipsoids

# Up direction of each capture in its own file frame (checked by plotting them): the
# plant (COLMAP, y down) and the tree mesh are upside down along y; the ring stands
# up along +y (as an arch, its gap at the bottom); the torus (axis y) and donut are z-up.
CAPTURE_UP: dict[str, tuple[float, float, float]] = {
    "plant.splat": (0.0, -1.0, 0.0),
    "tree_100k.splat": (0.0, -1.0, 0.0),
    "ring_100k.splat": (0.0, 1.0, 0.0),
    "ring_10k.splat": (0.0, 1.0, 0.0),
    "torus_100k.splat": (0.0, 0.0, 1.0),
    "donut_fused.ply": (0.0, 0.0, 1.0),
}

# Percentiles of the centres that define a capture's extent, so floaters do not set its size.
ROBUST_PERCENTILES = (0.5, 99.5)

# capture_arena: (file, footprint centre x, y in metres).
CAPTURE_ARENA_LAYOUT = (
    ("plant.splat", (-1.0, -0.8)),
    ("ring_100k.splat", (1.0, -0.8)),
    ("tree_100k.splat", (0.0, 1.0)),
)
CAPTURE_ARENA_FLOOR_M = 4.0
CAPTURE_ARENA_FLOOR_SPACING_M = 0.025

TILED_ROOM_SIZE_M = (10.0, 10.0, 3.0)
TILED_ROOM_FLOOR_SPACING_M = 0.03
# Slots for the copies: a square grid of this pitch (m) on the floor and on a second
# level at TILED_ROOM_LEVELS_M (the benchmark is about volume, not about gravity).
TILED_ROOM_PITCH_M = 1.25
TILED_ROOM_LEVELS_M = (0.0, 1.5)
TILED_ROOM_JITTER_M = 0.1


def similarity(ell: Ellipsoids, scale: float = 1.0, rotation=None, translation=None) -> Ellipsoids:
    """The image of ``ell`` under p -> scale * rotation @ p + translation (a new set).

    ``rotation`` must be a proper rotation (det +1), so each splat's axes are simply
    turned and its sigmas scaled; this is about twice as fast as a general 4x4 transform.
    """
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0):
        raise ValueError("similarity: rotation must be a proper 3x3 rotation matrix")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError("similarity: scale must be a positive number")
    t = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
    return Ellipsoids(
        centers=ell.centers @ (scale * R).T + t,
        rotations=np.matmul(R, ell.rotations),
        sigmas=ell.sigmas * scale,
        k=ell.k,
        opacity=ell.opacity,
        colors=ell.colors,
    )


def rotation_to_z_up(up) -> np.ndarray:
    """The 3x3 rotation that takes the unit vector ``up`` to +z (the shortest turn)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    c = float(u @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    V = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + V + V @ V / (1.0 + c)


def rotation_z(yaw: float) -> np.ndarray:
    """Rotation by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def normalize_to_size(ell: Ellipsoids, size_m: float = 1.0, rotation=None) -> Ellipsoids:
    """Scale and move ``ell`` so its robust extent has longest side ``size_m`` metres,
    is centred on the origin in x and y, and starts at z = 0.

    The extent is that of the centres between the 0.5 and 99.5 percentiles, so floaters
    do not set it; every splat is kept. Centres and sigmas scale together. If
    ``rotation`` (a proper 3x3 rotation) is given, the set is first turned by it (in the
    same single pass).
    """
    if len(ell) == 0:
        raise PolyccError("normalize_to_size: the set is empty; load a scene with splats in it")
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    lo, hi = np.percentile(ell.centers @ R.T, ROBUST_PERCENTILES, axis=0)
    side = float(np.max(hi - lo))
    if not side > 0:
        raise PolyccError("normalize_to_size: the splat centres have zero extent; nothing to scale")
    s = size_m / side
    mid = 0.5 * (lo + hi)
    return similarity(ell, s, rotation=R, translation=-s * np.array([mid[0], mid[1], lo[2]]))


def load_capture(path, size_m: float = 1.0, up=None) -> Ellipsoids:
    """Read a capture with default scene options, turn its ``up`` (default: from
    :data:`CAPTURE_UP`, else +z) to +z, and :func:`normalize_to_size` it to ``size_m``."""
    from polycc.scene.load import SceneOptions, load_scene

    path = Path(path)
    if not path.is_file():
        raise PolyccError(f"{path}: capture not found; pass the shared scenes directory (../shared/scenes)")
    ell = load_scene(path, SceneOptions()).ellipsoids
    up = CAPTURE_UP.get(path.name, (0.0, 0.0, 1.0)) if up is None else up
    return normalize_to_size(ell, size_m, rotation=rotation_to_z_up(up))


def capture_arena(scenes_dir, seed: int = 0, size_m: float = 1.0) -> Ellipsoids:
    """The arena of real captures: plant, ring (standing, as an arch) and tree, each
    ``size_m`` metres across, on a 4 m x 4 m floor of splats centred on the origin.

    About 340k splats. Placements are :data:`CAPTURE_ARENA_LAYOUT`; ``seed`` only moves
    the floor splats.
    """
    scenes_dir = Path(scenes_dir)
    rng = np.random.default_rng(seed)
    h = CAPTURE_ARENA_FLOOR_M / 2
    parts = [make_floor(rng, (-h, -h), (h, h), spacing=CAPTURE_ARENA_FLOOR_SPACING_M)]
    for name, (x, y) in CAPTURE_ARENA_LAYOUT:
        parts.append(similarity(load_capture(scenes_dir / name, size_m), translation=(x, y, 0.0)))
    return Ellipsoids.concatenate(parts)


def capture_files(scenes_dir) -> list[Path]:
    """Every ``.splat`` and ``.ply`` capture in ``scenes_dir``, sorted by name."""
    scenes_dir = Path(scenes_dir)
    files = sorted(p for p in scenes_dir.iterdir() if p.suffix.lower() in (".splat", ".ply"))
    if not files:
        raise PolyccError(f"{scenes_dir}: no .splat or .ply captures here; pass the shared scenes directory")
    return files


def tiled_room(scenes_dir, target: int = 1_500_000, seed: int = 0, size_m: float = 1.0) -> Ellipsoids:
    """The benchmark scene: a 10 m x 10 m x 3 m room (x, y in [-5, 5], floor at z = 0)
    with a floor of splats and copies of every capture in ``scenes_dir`` (each ``size_m``
    across, turned by a random yaw, in random grid slots on the floor and on a second
    level at 1.5 m) until exactly ``target`` splats (the last copy is a random subset).
    Deterministic in ``seed``.
    """
    rng = np.random.default_rng(seed)
    W, D, _H = TILED_ROOM_SIZE_M
    floor = make_floor(rng, (-W / 2, -D / 2), (W / 2, D / 2), spacing=TILED_ROOM_FLOOR_SPACING_M)
    if target <= len(floor):
        return floor.subset(np.sort(rng.choice(len(floor), size=target, replace=False)))
    assets = [load_capture(p, size_m) for p in capture_files(scenes_dir)]

    nx, ny = int(W // TILED_ROOM_PITCH_M), int(D // TILED_ROOM_PITCH_M)
    gx = (np.arange(nx) - (nx - 1) / 2) * TILED_ROOM_PITCH_M
    gy = (np.arange(ny) - (ny - 1) / 2) * TILED_ROOM_PITCH_M
    slots = np.array([(x, y, z) for z in TILED_ROOM_LEVELS_M for y in gy for x in gx])
    slots = slots[rng.permutation(len(slots))]

    parts, total, i = [floor], len(floor), 0
    order: list[int] = []
    while total < target:
        if i >= len(slots):
            raise PolyccError(
                f"tiled_room: {target:,} splats do not fit in {len(slots)} slots; lower the target"
            )
        if not order:  # every capture once per round, in random order
            order = list(rng.permutation(len(assets)))
        a = assets[order.pop()]
        need = target - total
        if len(a) > need:
            a = a.subset(np.sort(rng.choice(len(a), size=need, replace=False)))
        jitter = rng.uniform(-TILED_ROOM_JITTER_M, TILED_ROOM_JITTER_M, size=2)
        t = slots[i] + np.array([jitter[0], jitter[1], 0.0])
        parts.append(similarity(a, rotation=rotation_z(rng.uniform(0.0, 2.0 * np.pi)), translation=t))
        total += len(a)
        i += 1
    return Ellipsoids.concatenate(parts)
