"""Files for tests and benchmarks: the real captures beside the checkout, and small synthetic .ply files."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

CHECKOUT = Path(__file__).resolve().parents[2]
# The real splat captures (../shared/scenes beside the checkout; POLYCC_SHARED_SCENES overrides it).
SCENES = Path(os.environ.get("POLYCC_SHARED_SCENES", CHECKOUT.parent / "shared" / "scenes"))
# The Crazyflie firmware source tarballs (../shared/firmware; POLYCC_SHARED_FIRMWARE overrides it).
FIRMWARE = Path(os.environ.get("POLYCC_SHARED_FIRMWARE", CHECKOUT.parent / "shared" / "firmware"))


def write_ply(path: Path, columns: dict[str, np.ndarray], text: bool = False) -> Path:
    """Write a one-element 'vertex' .ply with the given float32 columns, in the given order."""
    from plyfile import PlyData, PlyElement

    n = len(next(iter(columns.values())))
    arr = np.empty(n, dtype=[(k, "f4") for k in columns])
    for k, v in columns.items():
        arr[k] = v
    PlyData([PlyElement.describe(arr, "vertex")], text=text).write(str(path))
    return path


def gaussian_columns(n: int, seed: int = 0, scale_log=(-5.0, -3.0)) -> dict[str, np.ndarray]:
    """Random pre-activation 3DGS columns (graphdeco names, minimal subset)."""
    rng = np.random.default_rng(seed)
    cols = {
        "x": rng.uniform(-1, 1, n), "y": rng.uniform(-1, 1, n), "z": rng.uniform(0, 1, n),
        "opacity": rng.normal(0, 2, n),
    }
    for i in range(3):
        cols[f"scale_{i}"] = rng.uniform(*scale_log, n)
    q = rng.normal(size=(n, 4))
    for i in range(4):
        cols[f"rot_{i}"] = q[:, i]
    return cols


def firmware_tarball(kind: str) -> Path:
    """The shared firmware fixture: ``kind`` ``"sitl"`` (CrazySim SITL fork) or ``"upstream"`` (bitcraze);
    ``POLYCC_SITL_TREE`` / ``POLYCC_UPSTREAM_TREE`` override it with a tree folder or another tarball."""
    env = {"sitl": "POLYCC_SITL_TREE", "upstream": "POLYCC_UPSTREAM_TREE"}[kind]
    if os.environ.get(env):
        return Path(os.environ[env])
    pattern = "crazyflie-firmware-sitl-*.tar.xz" if kind == "sitl" else "crazyflie-firmware-[0-9a-f]*.tar.xz"
    found = sorted(FIRMWARE.glob(pattern))
    return found[-1] if found else FIRMWARE / pattern


def sitl_tarball() -> Path:
    return firmware_tarball("sitl")


def upstream_tarball() -> Path:
    return firmware_tarball("upstream")


def readme_block(marker: str) -> str:
    """The python code block after ``<!-- MARKER -->`` in the checkout's README.md (the examples the tests
    run as written)."""
    import re

    m = re.search(rf"<!-- {re.escape(marker)} -->\n```python\n(.*?)```", (CHECKOUT / "README.md").read_text(), re.S)
    if m is None:
        raise AssertionError(f"README.md lost its example marked <!-- {marker} -->")
    return m.group(1)
