"""polycc: certified polytope obstacle covers from 3D Gaussian Splatting scenes for Crazyflie firmware.

The pipeline, one folder per stage: ``scene`` (splat files -> ellipsoids, metres) -> ``occupancy``
(exact voxels V+) -> ``cover`` (PolyMerge family) -> ``budget`` (reduce, quantize, choose n) ->
``codegen`` (``polytopes.h``), with ``onboard`` the Python side of the C contract and ``verify``
the independent checker. The curated API (numpy-style docstrings, world frame, metres)::

    scene = polycc.load_scene("room.ply", polycc.SceneOptions(scale=0.5))
    grid = polycc.voxelize(scene.ellipsoids, 0.05)
    family = polycc.build_cover(grid)
    result = polycc.build("room.ply", "out/room")            # what `polycc build` does
    report = polycc.verify("out/room", scene.ellipsoids.centers, scene.ellipsoids.axes(),
                           grid.indices, grid.voxel_size, grid.origin)

Names are imported on first use, so ``import polycc`` (and the CLI) stays fast.
"""

from polycc.version import __version__

__all__ = ["SceneOptions", "build", "build_cover", "load_scene", "verify", "voxelize", "__version__"]

_LAZY = {
    "load_scene": ("polycc.scene.load", "load_scene"),
    "SceneOptions": ("polycc.scene.load", "SceneOptions"),
    "voxelize": ("polycc.occupancy.exact", "voxelize"),
    "build_cover": ("polycc.cover.build", "build_cover"),
    "build": ("polycc.pipeline", "build"),
    "verify": ("polycc.verify", None),
}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'polycc' has no attribute {name!r}")
    import importlib

    mod, attr = _LAZY[name]
    m = importlib.import_module(mod)
    return m if attr is None else getattr(m, attr)
