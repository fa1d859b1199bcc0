"""Ellipsoids -> the exact voxel occupancy V+ (PolyMerge Sec. V-A), world frame, metres.

:func:`voxelize` (:mod:`.exact`) marks a voxel occupied iff it meets a splat ellipsoid (float
error counted toward "occupied"); :class:`OccupancyGrid` (:mod:`.grid`) holds the integer voxel
indices; :mod:`.floaters` computes what the optional floater filter gives up.
"""

from polycc.occupancy.exact import voxelize
from polycc.occupancy.grid import OccupancyGrid

__all__ = ["OccupancyGrid", "voxelize"]
