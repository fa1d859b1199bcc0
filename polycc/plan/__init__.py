"""Navigation through the certified free space of a build (world frame, metres).

:func:`plan_path` (or :class:`NavMap` for many queries on one map) plans from a start to a goal
on the stored polytopes at the agent radius, so that the path is free against what the drone's
barrier computes: every point has a certified lower bound of psi >= margin
(:mod:`polycc.plan.certified`). :class:`FreeSpace` checks start and goal before a flight
(``preflight``). Not part of the build pipeline; used by ``polycc plan`` and ``polycc sim --plan``.
"""

from polycc.plan.planner import (
    PLAN_FORMAT,
    REASONS,
    FreeSpace,
    NavMap,
    NoPathError,
    Plan,
    plan_path,
    read_plan,
)

__all__ = ["PLAN_FORMAT", "REASONS", "FreeSpace", "NavMap", "NoPathError", "Plan", "plan_path", "read_plan"]
