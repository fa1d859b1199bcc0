"""The sparse occupancy grid V+ (PolyMerge Sec. V-A): integer voxel indices plus g and origin.

Voxel ``i = (ix, iy, iz)`` is the closed box ``[origin + i*g, origin + (i+1)*g]`` in
metres, world frame. Voxel corners lie on ``origin + multiples of g``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError

NPZ_FORMAT = "polycc-occupancy/1"


@dataclass
class OccupancyGrid:
    """Occupied voxels.

    indices:    (N, 3) int64 voxel indices, sorted lexicographically, unique.
    voxel_size: g in metres.
    origin:     (3,) float64 metres; voxel i spans [origin + i g, origin + (i + 1) g].
    counts:     (N,) int32 number of distinct kept ellipsoids touching each voxel.
    stats:      free-form numbers for summaries (JSON-serialisable).
    removed:    (R, 3) int64 voxels the floater filter removed (touched by fewer than
                ``--min-splats-per-voxel`` ellipsoids), or None; the cover does not hold them.
    """

    indices: np.ndarray
    voxel_size: float
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    counts: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    removed: np.ndarray | None = None
    floater_loss: dict | None = None  # polycc.occupancy.floaters.floater_loss of ``removed``, when computed

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    def lower_corners(self) -> np.ndarray:
        """(N, 3) float64 minimum corner of each voxel, metres."""
        return self.origin + self.indices * self.voxel_size

    def centers(self) -> np.ndarray:
        """(N, 3) float64 voxel centres, metres."""
        return self.origin + (self.indices + 0.5) * self.voxel_size

    def volume(self) -> float:
        """Occupied volume, cubic metres."""
        return len(self) * self.voxel_size**3

    def save(self, path: str | Path) -> None:
        """Write an .npz with keys format, indices, voxel_size, origin, counts."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            format=np.array(NPZ_FORMAT),
            indices=self.indices.astype(np.int64),
            voxel_size=np.float64(self.voxel_size),
            origin=np.asarray(self.origin, dtype=np.float64),
            counts=(np.ones(len(self), np.int32) if self.counts is None else self.counts).astype(np.int32),
        )

    @staticmethod
    def load(path: str | Path) -> "OccupancyGrid":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                if "format" not in z or str(z["format"]) != NPZ_FORMAT:
                    raise PolyccError(f"{path}: not a polycc occupancy file; make one with `polycc voxelize SCENE -o "
                                      f"{path.name}`")
                return OccupancyGrid(
                    indices=z["indices"].astype(np.int64),
                    voxel_size=float(z["voxel_size"]),
                    origin=z["origin"].astype(np.float64),
                    counts=z["counts"].astype(np.int32),
                )
        except FileNotFoundError:
            raise PolyccError(f"{path}: no such file; make one with `polycc voxelize SCENE -o {path.name}`") from None
        except (OSError, ValueError, KeyError) as exc:
            raise PolyccError(f"{path}: cannot read occupancy file ({exc}); re-create it with `polycc "
                              "voxelize`") from None
