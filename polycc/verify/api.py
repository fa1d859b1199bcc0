"""``polycc.verify(...)``: certify a build or cover folder against the occupancy and ellipsoids given.

Takes plain arrays so that the checker stays independent of the pipeline: the caller derives
the occupied voxels and the kept ellipsoids from the scene again (``polycc verify`` does).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from polycc.errors import PolyccError
from polycc.verify.certify import (
    VerifyReport,
    certify_all_levels,
    check_level,
    default_levels,
    read_family,
    read_stored,
)


def verify(path: str | Path, centers: np.ndarray, axes: np.ndarray, indices: np.ndarray, voxel_size: float,
           origin, levels: list[int] | str | None = None, all_levels_certificate: bool = True,
           samples_per_ellipsoid: int = 64, min_samples: int = 1_000_000, mc_samples: int = 200_000,
           seed: int = 0, progress: Callable[[str, int, int], None] | None = None) -> VerifyReport:
    """Independently certify the cover in ``path`` (a ``polycc build`` or ``polycc cover`` folder).

    Parameters
    ----------
    path : the folder; for a build its ``manifest.json`` (the stored polytopes exactly as the C
        decodes them) is checked, for a cover its ``cover.npz`` (every level of the merge family).
    centers, axes : (E, 3) ellipsoid centres and (E, 3, 3) matrices L with E_i = {c_i + L_i u :
        |u| <= 1}, world frame, metres (``Ellipsoids.centers``, ``Ellipsoids.axes()``).
    indices, voxel_size, origin : the occupied voxels V+ (voxel i spans [origin + i g,
        origin + (i + 1) g], metres).
    levels : levels n checked directly, or ``"all"`` (default: N, 150, 100, 50, 30, 10, 1; a build
        has one level).
    all_levels_certificate : also certify (a) at every level through the merge sequence.
    samples_per_ellipsoid, min_samples : points sampled on and in each ellipsoid for (b).
    mc_samples : Monte Carlo samples per level for the conservativeness (c).
    progress : ``progress(stage, done, total)``.

    Returns
    -------
    VerifyReport: per level the voxels and points checked and uncovered, the conservativeness
    with its 95 % half-width; ``ok`` is True only if every voxel and every sampled point is inside.
    """
    path = Path(path)
    stored = (path / "manifest.json").exists() if path.is_dir() else path.suffix == ".json"
    try:
        fam = read_stored(path, voxel_size, origin) if stored else read_family(path)
    except FileNotFoundError:
        raise PolyccError(f"{path}: no cover.npz or manifest.json there; make it with `polycc cover` or "
                          f"`polycc build SCENE -o {path}`") from None
    except (OSError, ValueError, KeyError) as exc:
        raise PolyccError(f"{path}: not a readable cover ({exc}); re-create it with `polycc cover` or "
                          "`polycc build`") from None
    N = fam.n_leaves
    levels = [N] if stored else list(range(N, 0, -1)) if levels == "all" else (levels or default_levels(N))
    bad = [n for n in levels if not 1 <= n <= N]
    if bad:
        raise PolyccError(f"--levels: {bad} outside 1..{N}, the levels this cover holds")
    idx = np.asarray(indices, np.int64)
    rep = VerifyReport(voxels=len(idx))
    rep.stored = stored
    rep.grid_matches_cover = stored or bool(
        voxel_size == fam.g and np.array_equal(np.asarray(origin), fam.origin)
        and np.array_equal(idx, fam.grid_indices))
    if all_levels_certificate and N > 1 and not stored:
        report = (lambda k: progress("certificate", k, N - 1)) if progress else None
        fails = certify_all_levels(fam, idx, progress=report)
        rep.certificate_levels = N
        rep.certificate_failures = [{"n": n, "uncovered_voxels": u} for n, u in fails]
    rng = np.random.default_rng(seed)
    for k, n in enumerate(levels):
        rep.levels.append(check_level(fam, n, idx, centers, axes, samples_per_ellipsoid, min_samples, mc_samples, rng))
        if progress:
            progress("levels", k + 1, len(levels))
    return rep
