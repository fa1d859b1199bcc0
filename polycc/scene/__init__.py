"""Splat files -> :class:`Ellipsoids` in the world frame, metres.

Readers (:mod:`.readers`: 3DGS .ply, point-cloud .ply, .splat), writers (:mod:`.writers`), the
trainer-frame -> world transform (:mod:`.transform`) and :func:`load_scene`, which validates,
transforms, filters and crops while counting everything it drops (:mod:`.load`).
"""

from polycc.scene.ellipsoids import Ellipsoids
from polycc.scene.load import Scene, SceneOptions, SceneStats, load_scene

__all__ = ["Ellipsoids", "Scene", "SceneOptions", "SceneStats", "load_scene"]
