"""Scene settings: every option that decides the geometry a build certifies (world frame, metres).

:class:`SceneSettings` holds the scene options (sigma, opacity filter, transform, crop, invalid
splats) and the occupancy options (voxel size, floater filter) of one build, records them in
``manifest.json``/``cover.npz`` (:meth:`SceneSettings.as_record`) and reads them back
(:func:`recorded_settings`), so that commands reading a build folder use exactly its geometry.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.scene.load import SceneOptions, file_sha256
from polycc.scene.transform import load_transform, scale_matrix

SCENE_DEFAULTS = {
    "sigma": 1.0, "min_opacity": 0.0, "transform": None, "scale": None, "crop": None, "drop_invalid": False,
    "voxel": 0.05, "min_splats_per_voxel": 1, "drop_isolated": None,
}
_IDENTITY = np.eye(4)


@dataclass
class SceneSettings:
    """Every scene option of one run, after defaults and the build's record are applied.

    ``world_matrix`` is the 4x4 file -> world (metres) matrix that ``transform`` (a JSON file,
    kept for provenance) and ``scale`` compose to; it is what is recorded and compared, so a
    build folder stays usable when the transform file moves."""

    sigma: float = 1.0
    min_opacity: float = 0.0
    transform: str | None = None
    scale: float | None = None
    crop: tuple | None = None
    drop_invalid: bool = False
    voxel: float = 0.05
    min_splats_per_voxel: int = 1
    drop_isolated: tuple | None = None
    world_matrix: np.ndarray = field(default_factory=lambda: np.eye(4))

    def scene_options(self) -> SceneOptions:
        T = np.asarray(self.world_matrix, np.float64)
        return SceneOptions(sigma=self.sigma, min_opacity=self.min_opacity,
                            transform=None if np.array_equal(T, _IDENTITY) else T, scale=None,
                            crop=None if self.crop is None else tuple(self.crop), drop_invalid=self.drop_invalid,
                            drop_isolated=None if self.drop_isolated is None else
                            (float(self.drop_isolated[0]), int(self.drop_isolated[1])))

    def as_record(self) -> dict:
        """JSON-ready record (manifest.json ``scene_settings``, cover.npz meta)."""
        return {"sigma": self.sigma, "min_opacity": self.min_opacity, "transform": self.transform,
                "scale": self.scale, "crop": None if self.crop is None else list(self.crop),
                "drop_invalid": self.drop_invalid, "voxel": self.voxel,
                "min_splats_per_voxel": self.min_splats_per_voxel,
                "drop_isolated": None if self.drop_isolated is None else list(self.drop_isolated),
                "world_matrix": np.asarray(self.world_matrix, np.float64).tolist()}

    @staticmethod
    def from_record(rec: dict) -> "SceneSettings":
        kw = {k: rec.get(k, v) for k, v in SCENE_DEFAULTS.items()}
        if kw["crop"] is not None:
            kw["crop"] = tuple(float(c) for c in kw["crop"])
        if kw["drop_isolated"] is not None:
            kw["drop_isolated"] = (float(kw["drop_isolated"][0]), int(kw["drop_isolated"][1]))
        T = rec.get("world_matrix")
        return SceneSettings(**kw, world_matrix=np.eye(4) if T is None else np.asarray(T, np.float64))


def world_matrix(transform: str | None, scale: float | None) -> np.ndarray:
    T = load_transform(transform) if transform else np.eye(4)
    return scale_matrix(scale) @ T if scale is not None else T


def recorded_settings(path: str | Path) -> tuple[SceneSettings | None, dict]:
    """(scene settings, scene record {name, path, sha256}) that a `polycc build` or `polycc cover`
    folder was made with; (None, {}) when it records none."""
    path = Path(path)
    man = path / "manifest.json" if path.is_dir() else path
    if man.suffix == ".json" and man.is_file():
        try:
            m = json.loads(man.read_text())
        except (OSError, ValueError) as exc:
            raise PolyccError(f"{man}: not readable JSON ({exc}); rebuild with `polycc build`") from None
        rec = m.get("scene_settings")
        if rec is None and "options" in m:  # manifests written before scene_settings
            rec = dict(m["options"])
            rec["world_matrix"] = m.get("transform")
        return (SceneSettings.from_record(rec) if rec else None), m.get("scene", {})
    npz = path / "cover.npz" if path.is_dir() else path
    if npz.suffix == ".npz" and npz.is_file():
        try:
            with np.load(npz, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"])) if "meta" in z else {}
        except (OSError, ValueError) as exc:
            raise PolyccError(f"{npz}: not a readable cover file ({exc}); re-create it with `polycc cover`") from None
        rec = meta.get("scene_settings")
        scene = {"path": meta.get("scene"), "sha256": meta.get("scene_sha256")}
        return (SceneSettings.from_record(rec) if rec else None), scene
    return None, {}


def check_scene_file(scene_path: str | Path, recorded_scene: dict, source: str) -> None:
    """An explicit scene file must be the one the build was made from (same sha256)."""
    sha = recorded_scene.get("sha256")
    if not sha:
        return
    p = Path(scene_path)
    if not p.is_file():
        raise PolyccError(f"{p}: no such scene file; check the path")
    have = file_sha256(p)
    if have != sha:
        raise PolyccError(
            f"{p} (sha256 {have[:12]}...) is not the scene {source} was built from "
            f"({recorded_scene.get('path', '?')}, sha256 {sha[:12]}...); pass that scene, or rebuild from this one")
