"""Scene ingest: read a splat file, validate it, move it to metres, filter, crop.

Nothing is dropped silently: :class:`SceneStats` counts every splat read, and how many
were invalid (NaN/Inf or a degenerate quaternion), below ``min_opacity`` or outside
the crop box. Invalid splats are refused unless ``drop_invalid`` is set.
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.geometry.ellipsoid_box import boxes_intersect
from polycc.scene.ellipsoids import SIGMA_FLOOR_M, Ellipsoids, quaternion_to_rotation
from polycc.scene.quantized import inflated_sigmas
from polycc.scene.readers import read_splats
from polycc.scene.transform import apply_transform, check_transform, scale_matrix

# A quaternion shorter than this (before normalisation) has no defined rotation.
QUAT_MIN_NORM = 1e-6


@dataclass
class SceneOptions:
    """How to read a scene. Lengths in metres after the transform.

    sigma:        k, the ellipsoid is the k-sigma level set.
    min_opacity:  drop splats with activated opacity below this (0 keeps all).
    transform:    4x4 matrix from the file's frame to the world frame (metres), or None.
    scale:        uniform scale applied after ``transform`` (None = 1).
    crop:         (xmin, ymin, zmin, xmax, ymax, zmax) metres, world frame; keeps every
                  ellipsoid that meets the box, including those that straddle its boundary.
    drop_invalid: skip NaN/Inf splats and degenerate quaternions instead of refusing.
    drop_isolated: (R metres, N splats) or None: the splat-level floater filter, drop every group of
                  fewer than N splats whose centres (binned in cells of side R, world frame) touch no
                  other group (:func:`polycc.scene.survey.splat_groups`); the cover is then certified
                  against the kept splats and the dropped groups are listed.
    """

    sigma: float = 1.0
    min_opacity: float = 0.0
    transform: np.ndarray | None = None
    scale: float | None = None
    crop: tuple[float, float, float, float, float, float] | None = None
    drop_invalid: bool = False
    drop_isolated: tuple[float, int] | None = None

    def world_matrix(self) -> np.ndarray:
        T = np.eye(4) if self.transform is None else np.asarray(self.transform, np.float64)
        if self.scale is not None:
            T = scale_matrix(self.scale) @ T
        return T


@dataclass
class SceneStats:
    read: int = 0
    invalid: int = 0
    invalid_nonfinite: int = 0
    invalid_quaternion: int = 0
    invalid_saturated: int = 0
    filtered_opacity: int = 0
    cropped: int = 0
    triangles: int = 0
    dropped_isolated: int = 0
    triangles_cropped: int = 0
    sigma_floored: int = 0
    quantized_inflated: int = 0
    kept: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Scene:
    path: Path
    ellipsoids: Ellipsoids
    options: SceneOptions
    stats: SceneStats = field(default_factory=SceneStats)
    sha256: str = ""
    info: dict = field(default_factory=dict)  # format details from the reader (format, version, quantization)
    triangles: np.ndarray | None = None  # (T, 3, 3) mesh triangles, world frame, metres (mesh .ply only)
    dropped_groups: list = field(default_factory=list)  # splat-level floater filter: survey.Group of each


def file_sha256(path: Path, stop: threading.Event | None = None) -> str:
    """The file's SHA-256, hex ("" if ``stop`` is set before the end)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            if stop is not None and stop.is_set():
                return ""
            h.update(block)
    return h.hexdigest()


class _BackgroundSha256:
    """:func:`file_sha256` on a thread while the scene is parsed (reads and hashlib release the GIL: 0.6-1 s of a
    6M-splat room's 6 s read saved); :meth:`result` waits for it, :meth:`cancel` stops it early."""

    def __init__(self, path: Path):
        self.stop, self.out = threading.Event(), {}
        self.thread = threading.Thread(target=self._run, args=(path,), name="polycc-sha256", daemon=True)
        self.thread.start()

    def _run(self, path: Path) -> None:
        try:
            self.out["sha"] = file_sha256(path, self.stop)
        except OSError as exc:  # the reader reports an unreadable file itself
            self.out["error"] = exc

    def result(self) -> str:
        self.thread.join()
        if "error" in self.out:
            raise self.out["error"]
        return self.out["sha"]

    def cancel(self) -> None:
        self.stop.set()


def load_scene(path: str | Path, opts: SceneOptions | None = None) -> Scene:
    """Read, validate, transform, filter and crop a scene file.

    Parameters
    ----------
    path : a 3DGS .ply (graphdeco layout, any property order), SuperSplat .compressed.ply, Niantic .spz,
        a mesh .ply, a point-cloud .ply (x y z [radius]) or an antimatter15 .splat file.
    opts : sigma (the k-sigma ellipsoid), opacity filter, 4x4 trainer-frame -> world transform
        (metres), uniform scale, crop box (metres, world frame), whether to drop invalid splats.

    Returns
    -------
    Scene with ``ellipsoids`` (world frame, metres), ``stats`` counting every splat read,
    invalid, filtered and cropped (nothing is dropped silently) and the file's ``sha256``.

    Raises PolyccError (one line: the file, the problem and the fix) on bad input.
    """
    opts = opts or SceneOptions()
    path = Path(path)
    _check_options(opts)
    sha = _BackgroundSha256(path) if path.is_file() else None
    try:
        return _load(path, opts, sha)
    finally:
        if sha is not None:
            sha.cancel()  # after an error; a no-op once the hash is done


def _load(path: Path, opts: SceneOptions, sha: _BackgroundSha256 | None) -> Scene:
    raw = read_splats(path)
    stats = SceneStats(read=int(raw.positions.shape[0]))
    if stats.read == 0:
        raise PolyccError(f"{path}: the file holds zero splats; export a scene with Gaussians in it")

    # -- validity: finite numbers and a usable quaternion
    finite, qn = _finite_rows(raw)
    if raw.quats is not None:
        bad_q = finite & (qn < QUAT_MIN_NORM)
    else:
        bad_q = np.zeros(stats.read, bool)
    if raw.bounds is not None:  # a saturated size code: the true splat may be any size
        finite &= np.isfinite(raw.bounds.pos_err).all(axis=1) & np.isfinite(raw.bounds.quat_err)
        bad_sat = finite & ~bad_q & raw.bounds.saturated()
    else:
        bad_sat = np.zeros(stats.read, bool)
    stats.invalid_nonfinite = int((~finite).sum())
    stats.invalid_quaternion = int(bad_q.sum())
    stats.invalid_saturated = int(bad_sat.sum())
    valid = finite & ~bad_q & ~bad_sat
    stats.invalid = stats.read - int(valid.sum())
    if stats.invalid and not opts.drop_invalid:
        parts = []
        if stats.invalid_nonfinite:
            parts.append(f"{stats.invalid_nonfinite} splats with NaN/Inf values")
        if stats.invalid_quaternion:
            parts.append(f"{stats.invalid_quaternion} with a zero-length rotation quaternion")
        if stats.invalid_saturated:
            parts.append(f"{stats.invalid_saturated} whose size code is saturated at the format's maximum (the true "
                         "size is unbounded; re-export from the original .ply to keep them)")
        raise PolyccError(
            f"{path}: {' and '.join(parts)} (of {stats.read}); pass --drop-invalid to skip them, or fix the export"
        )

    # -- activations and frame (every splat valid, the usual case: the arrays read, not copies)
    sel = slice(None) if stats.invalid == 0 else valid
    sig = raw.sigmas[sel]
    if raw.quats is None:
        R = np.broadcast_to(np.eye(3), (int(valid.sum()), 3, 3)).copy()
        sig = sig / opts.sigma  # a point's radius is its extent whatever k is
    else:
        R = quaternion_to_rotation(raw.quats[sel], qn[sel])
        if raw.bounds is not None:  # quantized file: hold every splat the stored bits allow
            sig = inflated_sigmas(raw.bounds.subset(valid), float(opts.sigma))
            stats.quantized_inflated = int(len(sig))
    ell = Ellipsoids(
        centers=raw.positions[sel],
        rotations=R,
        sigmas=np.abs(sig),
        k=float(opts.sigma),
        opacity=raw.opacity[sel],
        colors=None if raw.colors is None else raw.colors[sel],
    )
    T = opts.world_matrix()
    if not np.array_equal(T, np.eye(4)):
        ell = apply_transform(ell, T)
    tris = None
    if raw.triangles is not None:
        tris = np.asarray(raw.triangles, np.float64) @ T[:3, :3].T + T[:3, 3]
        stats.triangles = int(len(tris))
        if not np.isfinite(tris).all():
            raise PolyccError(f"{path}: the mesh has NaN/Inf vertex coordinates; repair the mesh")
    small = ell.sigmas < SIGMA_FLOOR_M
    stats.sigma_floored = int(small.any(axis=1).sum())
    if stats.sigma_floored:
        ell.sigmas = np.maximum(ell.sigmas, SIGMA_FLOOR_M)

    # -- opacity filter
    if opts.min_opacity > 0:  # outward for quantized alpha: drop only if even its upper bound is below
        op_hi = (raw.opacity[sel].astype(np.float64) if raw.bounds is None
                 else np.maximum(raw.bounds.opacity_hi[sel], raw.opacity[sel]))
        keep = op_hi >= opts.min_opacity
        stats.filtered_opacity = int((~keep).sum())
        ell = ell.subset(keep)

    # -- crop (exact ellipsoid-box test; straddling ellipsoids are kept)
    if opts.crop is not None and len(ell):
        lo = np.asarray(opts.crop[:3], np.float64)
        hi = np.asarray(opts.crop[3:], np.float64)
        keep = crop_mask(ell, lo, hi)
        stats.cropped = int((~keep).sum())
        ell = ell.subset(keep)
        if tris is not None:  # keep every triangle whose box meets the crop box (straddling ones whole)
            tk = np.all((tris.min(axis=1) <= hi) & (tris.max(axis=1) >= lo), axis=1)
            stats.triangles_cropped = int((~tk).sum())
            tris = tris[tk]

    dropped_groups = []
    if opts.drop_isolated is not None and len(ell):
        from polycc.scene.survey import isolated_mask

        drop, dropped_groups = isolated_mask(ell.centers, float(opts.drop_isolated[0]), int(opts.drop_isolated[1]))
        if drop.any():
            stats.dropped_isolated = int(drop.sum())
            ell = ell.subset(~drop)

    stats.kept = len(ell)
    if stats.kept == 0:
        why = []
        if stats.invalid:
            why.append(f"{stats.invalid} invalid")
        if stats.filtered_opacity:
            why.append(f"{stats.filtered_opacity} below --min-opacity {opts.min_opacity:g}")
        if stats.cropped:
            why.append(f"{stats.cropped} outside --crop")
        raise PolyccError(
            f"{path}: zero splats left after filtering ({', '.join(why)} of {stats.read} read); "
            "lower --min-opacity or widen --crop (the crop box is in metres, after --transform/--scale)"
        )
    digest = sha.result() if sha is not None else file_sha256(path)
    return Scene(path=path, ellipsoids=ell, options=opts, stats=stats, sha256=digest, info=dict(raw.info),
                 triangles=tris, dropped_groups=dropped_groups)


def _finite_rows(raw) -> tuple[np.ndarray, np.ndarray | None]:
    """(N,) bool: the splat's position, sigmas, opacity (and quaternion) are finite; (N,) the length of its
    quaternion with non-finite entries taken as 0 (None for points). In row chunks on every core."""
    from polycc.parallel import in_row_chunks

    n = len(raw.positions)
    finite = np.empty(n, bool)
    qn = None if raw.quats is None else np.empty(n)

    def rows(s: int, e: int) -> None:
        f = np.isfinite(raw.positions[s:e]).all(axis=1) & np.isfinite(raw.sigmas[s:e]).all(axis=1) \
            & np.isfinite(raw.opacity[s:e])
        if qn is not None:
            q = raw.quats[s:e]
            ok = np.isfinite(q)
            f &= ok.all(axis=1)
            qn[s:e] = np.linalg.norm(np.where(ok, q, 0.0), axis=1)
        finite[s:e] = f

    in_row_chunks(n, rows)
    return finite, qn


def crop_mask(ell: Ellipsoids, lo: np.ndarray, hi: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """(N,) bool: ellipsoid meets the box [lo, hi] (metres)."""
    keep = np.zeros(len(ell), bool)
    h = ell.aabb_halfwidth()
    near = np.all((ell.centers + h >= lo) & (ell.centers - h <= hi), axis=1)
    idx = np.flatnonzero(near)
    for s in range(0, idx.size, chunk):
        sl = idx[s : s + chunk]
        sub = ell.subset(sl)
        keep[sl] = boxes_intersect(sub.centers, sub.whitening(), np.broadcast_to(lo, (sl.size, 3)),
                                   np.broadcast_to(hi, (sl.size, 3)))
    return keep


def _check_options(opts: SceneOptions) -> None:
    if not (np.isfinite(opts.sigma) and opts.sigma > 0):
        raise PolyccError(f"--sigma {opts.sigma}: must be a positive number of standard deviations (1 = paper, 3 = "
                          "render extent)")
    if not (0.0 <= opts.min_opacity <= 1.0):
        raise PolyccError(f"--min-opacity {opts.min_opacity}: must be between 0 and 1")
    if opts.scale is not None and not (np.isfinite(opts.scale) and opts.scale > 0):
        raise PolyccError(f"--scale {opts.scale}: must be a positive factor (file units to metres)")
    if opts.transform is not None:
        check_transform(np.asarray(opts.transform, np.float64), "--transform")
    if opts.drop_isolated is not None:
        r, n = opts.drop_isolated
        if not (np.isfinite(r) and r > 0 and int(n) >= 2):
            raise PolyccError(f"--drop-isolated {r:g},{n}: give a cell side R > 0 metres and a group size N >= 2")
    if opts.crop is not None:
        c = np.asarray(opts.crop, np.float64)
        if c.shape != (6,) or not np.all(np.isfinite(c)) or np.any(c[:3] >= c[3:]):
            raise PolyccError("--crop: give xmin,ymin,zmin,xmax,ymax,zmax in metres with each min < max")
