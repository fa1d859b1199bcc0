"""The library entry point: scene -> occupancy -> cover -> budget -> codegen.

:func:`build` does what ``polycc build`` does and returns a :class:`BuildResult`; the CLI only
parses options and prints. Stages report through ``progress(stage, done, total)`` (stage is one
of ``"read"``, ``"voxelize"``, ``"floaters"``, ``"cover"``, ``"budget"``, ``"write"``) so a caller
can show progress; the pipeline itself prints nothing. World frame, metres.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from polycc.budget import cycle_model
from polycc.budget.select import Budget, Candidate, select
from polycc.codegen.header import write_outputs
from polycc.cover.build import DEFAULT_MERGE_COST, build_cover
from polycc.cover.family import CoverFamily
from polycc.errors import PolyccError
from polycc.occupancy.estimate import HUGE_SPLAT_VOXELS, estimate, size_error
from polycc.occupancy.exact import voxelize
from polycc.occupancy.floaters import floater_loss, floater_text, loss_record
from polycc.occupancy.grid import OccupancyGrid
from polycc.occupancy.triangles import merge_triangles
from polycc.onboard.app import app_rate_hz
from polycc.onboard.index import DEFAULT_CLEARANCE_CAP
from polycc.onboard.layout import stored_vertices
from polycc.parallel import Runner, make_runner
from polycc.report.plots import write_report
from polycc.scene.load import Scene, load_scene
from polycc.scene.settings import SceneSettings
from polycc.scene.survey import extent_warning, robust_bounds

Progress = Callable[[str, float, float], None]
Warn = Callable[[str], None]
SLOW_VOXELS = 30_000_000  # warn (with the estimate) before voxelizing more than this


@dataclass
class BuildOptions:
    """Budgets and cover options of ``polycc build`` (see its ``--help`` for units and ranges)."""

    flash_kb: float = 64.0  # KiB of generated constant data
    max_halfplanes: int | None = None
    rate_hz: float | None = cycle_model.DEFAULT_RATE_HZ  # Hz; with cpu_share, bounds the certified worst case
    cpu_share: float = cycle_model.DEFAULT_CPU_SHARE
    clearance_cap: float | None = DEFAULT_CLEARANCE_CAP  # D, m, of the spatial index (None: no index)
    kappa: float = 100.0  # 1/m
    neighborhood: int = 1  # cluster radius b, voxels
    boxes: bool = True
    merge_cost: str = DEFAULT_MERGE_COST
    mc_samples: int = 100_000
    jobs: int | None = None  # local worker processes (None = every core); the result does not depend on it
    dask: str | None = None  # "tcp://HOST:PORT" of a Dask scheduler or "local:N"; overrides jobs

    def budget(self) -> Budget:
        rate = cycle_model.cycle_budget(self.rate_hz, self.cpu_share) if self.rate_hz is not None else None
        return Budget(int(self.flash_kb * 1024), self.max_halfplanes, rate, self.clearance_cap, self.kappa)


@dataclass
class BuildResult:
    out: Path
    scene: Scene
    occupancy: OccupancyGrid
    family: CoverFamily
    best: Candidate
    candidates: list[Candidate]
    binding: str
    modelled_us: dict
    manifest: dict
    timings_s: dict = field(default_factory=dict)


def read(scene_path: str | Path, settings: SceneSettings, progress: Progress | None = None,
         warn: Warn | None = None) -> Scene:
    """The scene with every scene option of ``settings`` applied; ``warn`` gets a line when its extent
    does not look metric (:func:`polycc.scene.survey.extent_warning`)."""
    if progress:
        progress("read", 0, 1)
    t = time.perf_counter()
    scene = load_scene(scene_path, settings.scene_options())
    scene.stats_time_s = time.perf_counter() - t
    msg = extent_warning(*robust_bounds(scene.ellipsoids.centers))
    if msg and warn:
        warn(msg)
    return scene


def check_size(scene: Scene, voxel: float, warn: Warn | None = None) -> None:
    """Before voxelizing: refuse a voxelization that cannot fit (one line, the fix), warn on a long one."""
    est = estimate(scene.ellipsoids, voxel, timed=False, at_least=False)
    if size_error(est):  # the refusal names the lower bound too: counted only then
        raise PolyccError(f"{scene.path}: {size_error(estimate(scene.ellipsoids, voxel, timed=False))}")
    if warn and (est.voxels_at_most > SLOW_VOXELS or est.huge_splats):
        big = (f"; {est.huge_splats:,} splats each span more than {HUGE_SPLAT_VOXELS:,} voxels (largest "
               f"{est.largest_splat_voxels:.3g})" if est.huge_splats else "")
        warn(f"large voxelization ahead: up to {est.voxels_at_most:.3g} voxels at {voxel:g} m (~{est.memory_gb:.1f} "
             f"GB){big}; `polycc info` estimates the time; a larger --voxel or --crop makes it smaller")


def occupancy(scene: Scene, settings: SceneSettings, progress: Progress | None = None,
              warn: Warn | None = None, runner: Runner | None = None) -> OccupancyGrid:
    """Exact V+ of the scene at ``settings.voxel``, with the floater filter's loss computed
    (x slabs in parallel on ``runner``'s workers, the same result)."""
    check_size(scene, settings.voxel, warn)
    n = len(scene.ellipsoids)
    t = time.perf_counter()
    occ = voxelize(scene.ellipsoids, settings.voxel, settings.min_splats_per_voxel,
                   progress=(lambda done: progress("voxelize", done, n)) if progress else None, runner=runner)
    if scene.triangles is not None and len(scene.triangles):
        nt = len(scene.triangles)
        occ = merge_triangles(occ, scene.triangles,
                              progress=(lambda done: progress("triangles", done, nt)) if progress else None)
    occ.stats["time_s"] = time.perf_counter() - t
    if settings.min_splats_per_voxel > 1 and occ.removed is not None and len(occ.removed):
        if progress:
            progress("floaters", 0, 1)
        occ.floater_loss = floater_loss(scene.ellipsoids, occ.indices, occ.removed, occ.voxel_size, occ.origin)
        occ.stats["floater_filter"] = loss_record(occ.floater_loss)
    if len(occ) == 0:
        raise PolyccError(
            f"{scene.path}: no voxel has {settings.min_splats_per_voxel} or more splats touching it; "
            "lower --min-splats-per-voxel or use a larger --voxel")
    return occ


def build(scene_path: str | Path, out: str | Path, settings: SceneSettings | None = None,
          options: BuildOptions | None = None, progress: Progress | None = None,
          warn: Warn | None = None) -> BuildResult:
    """Build the on-board scene of ``scene_path`` into the folder ``out``.

    Parameters
    ----------
    scene_path : a scene file: 3DGS .ply, .compressed.ply, .splat, .spz, point-cloud or mesh .ply.
    out : output folder (created): ``polytopes.h``, ``manifest.json``, ``scene.bin``, ``cover.npz``,
        ``report.png``.
    settings : scene and occupancy options (default: :class:`SceneSettings` defaults: sigma 1,
        no transform, 5 cm voxels).
    options : budgets and cover options (default: 64 KiB, no other budget).
    progress : ``progress(stage, done, total)``, called as the stages advance.
    warn : ``warn(line)`` for a non-metric extent or a large voxelization ahead (before the work).

    Returns
    -------
    BuildResult with the chosen candidate (``best``: n, half-planes, bytes, conservativeness with
    its 95 % half-width), every candidate measured, the binding budget, the modelled on-board
    time (typical and worst, microseconds at 168 MHz) and the manifest written.
    """
    t_all = time.perf_counter()
    settings = settings or SceneSettings()
    options = options or BuildOptions()
    budget = options.budget()
    out = Path(out)
    with make_runner(options.jobs, options.dask) as runner:
        scene = read(scene_path, settings, progress, warn)
        occ = occupancy(scene, settings, progress, warn, runner)
        t = time.perf_counter()
        family = build_cover(occ, b=options.neighborhood, cost=options.merge_cost, boxes=options.boxes, runner=runner,
                             progress=progress)
        t_cover = time.perf_counter() - t
        return _budget_and_write(scene_path, out, settings, options, budget, scene, occ, family, t_all, t_cover,
                                 progress, runner.local_cores)


def _budget_and_write(scene_path, out, settings, options, budget, scene, occ, family, t_all, t_cover, progress,
                      local_cores: int | None = None):
    out.mkdir(parents=True, exist_ok=True)
    family.meta.update({"scene_sha256": scene.sha256, "scene": str(scene_path),
                        "scene_settings": settings.as_record()})
    family.save(out / "cover.npz")

    t = time.perf_counter()
    best, cands, binding = select(family, budget, mc_samples=options.mc_samples,
                                  progress=(lambda d, n: progress("budget", d, n)) if progress else None,
                                  workers=local_cores, stage_progress=progress)
    t_budget = time.perf_counter() - t
    us = cycle_model.estimate_us(best.packed, options.kappa)
    if progress:
        progress("write", 0, 1)
    man = write_outputs(out, best.packed, _meta(scene_path, scene, occ, family, best, cands, binding, us, settings,
                                                options, budget))
    write_report(out / "report.png", scene.ellipsoids.centers,
                 [v if v is not None else np.zeros((1, 3)) for v in stored_vertices(best.packed)],
                 tradeoff_curve(cands), (best.n, best.conservativeness),
                 f"{Path(scene_path).name}: n = {best.n}, {best.n_planes} half-planes, {best.bytes} B of "
                 f"{budget.flash_bytes} B, conservativeness {best.conservativeness:.4f}")
    timings = {"occupancy": occ.stats.get("time_s", 0.0), "cover": t_cover, "budget": t_budget,
               "total": time.perf_counter() - t_all}
    return BuildResult(out, scene, occ, family, best, cands, binding, us, man, timings)


def tradeoff_curve(cands: list[Candidate]) -> list[tuple[int, float, float]]:
    """(n, conservativeness, 95 % half-width) of the least conservative candidate at each n."""
    per_n: dict = {}
    for c in cands:
        if c.n not in per_n or c.conservativeness < per_n[c.n].conservativeness:
            per_n[c.n] = c
    return [(c.n, c.conservativeness, c.conservativeness_ci) for _, c in sorted(per_n.items())]


def _meta(scene_path, scene, occ, family, best, cands, binding, us, settings, options, budget) -> dict:
    rec = settings.as_record()
    worst = int(np.ceil(us["worst_us"] * cycle_model.CPU_HZ / 1e6))
    # where it ran (jobs, dask) does not change the result, so it is not recorded: same input, same bytes
    opts = {**{k: v for k, v in rec.items() if k != "world_matrix"},
            **{k: v for k, v in asdict(options).items() if k not in ("jobs", "dask")}}
    stats = {
        "splats_read": scene.stats.read, "splats_kept": scene.stats.kept, "scene_stats": scene.stats.as_dict(),
        "voxels": len(occ), "voxel_size_m": occ.voxel_size, "occupied_volume_m3": occ.volume(),
        "n_subcover": family.n_max, "n": best.n, "halfplanes": best.n_planes,
        "halfplanes_before_reduction": best.planes_before, "halfplanes_dropped": best.dropped,
        "halfplanes_merged": best.merged,
        "normals": best.n_normals, "normals_before_reduction": best.normals_before,
        "normal_table_cap": best.max_normals, "quantum_m": float(best.packed.quantum),
        "bytes": best.bytes, "budget_bytes": budget.flash_bytes, "bytes_per_halfplane": best.bytes / best.n_planes,
        "max_halfplanes": min(best.caps.values()), "binding_budget": binding,
        "conservativeness": best.conservativeness, "conservativeness_ci95": best.conservativeness_ci,
        "union_volume_m3": best.union_volume, "modelled_us": us,
        "onboard": {"worst_us": us["worst_us"], "typical_us": us["typical_us"],
                    "worst_is_certified": best.packed.index is not None,
                    "worst_cycles": worst, "clearance_cap_m": None if best.packed.index is None else
                    float(best.packed.index.cap),
                    "index": None if best.packed.index is None else {
                        "cell_m": best.packed.index.cell, "dims": list(best.packed.index.dims),
                        "lists": best.packed.index.n_lists, "entries": len(best.packed.index.entries),
                        "bytes": best.packed.index.nbytes()}},
        "app_rate_hz": app_rate_hz(worst),  # the rate polycc_app.c runs this header at (None: refused)
        "floater_filter": occ.stats.get("floater_filter"),
        "dropped_isolated": [{"splats": g.count, "centroid_m": g.centroid.tolist(), "lo_m": g.lo.tolist(),
                              "hi_m": g.hi.tolist(), "distance_to_main_body_m": g.gap} for g in scene.dropped_groups],
        "candidates": [{"n": c.n, "normal_table_cap": c.max_normals, "normals": c.n_normals, "halfplanes": c.n_planes,
                        "dropped": c.dropped, "bytes": c.bytes, "conservativeness": c.conservativeness,
                        "ci95": c.conservativeness_ci} for c in cands],
    }
    identity = np.array_equal(np.asarray(rec["world_matrix"]), np.eye(4))
    return {
        "scene_settings": rec, "floater_line": floater_text(occ.stats) or "none (--min-splats-per-voxel 1)",
        "kappa": options.kappa, "budget_bytes": budget.flash_bytes, "max_planes": min(best.caps.values()),
        "worst_cycles": worst,
        "typical_cycles": int(np.ceil(us["typical_us"] * cycle_model.CPU_HZ / 1e6)),
        "binding": binding,
        "conservativeness_text": f"{best.conservativeness:.4f} +- {best.conservativeness_ci:.4f} (95% CI)",
        "options": opts, "transform": None if identity else rec["world_matrix"],
        "scene": {"name": Path(scene_path).name, "path": str(scene_path), "sha256": scene.sha256},
        "stats": stats,
    }
