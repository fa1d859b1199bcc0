"""Make the packed-format fixtures under tests/data/formats (run from the checkout root).

    python tools/make_format_fixtures.py [SPLAT_TRANSFORM]

1. writes tests/data/formats/synth.ply: 1,200 synthetic splats (14 float properties, graphdeco names)
   made to stress the formats: thin discs and needles, rotations near 180 degrees (w ~ 0), splats
   from 1 mm to 1 m, a floor and clusters metres apart (chunks that straddle them), and two splats
   whose log-scale (7) is above spz's top code, so their size is unbounded in .spz;
2. converts it with the ecosystem's converter, pinned: ``npx @playcanvas/splat-transform@3.7.0``
   (or the SPLAT_TRANSFORM executable given), to ``synth.compressed.ply``, ``synth.spz`` (v4) and
   ``synth.v3.spz``. Deterministic: the same inputs give the same bytes.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

OUT = Path("tests/data/formats")
VERSION = "3.7.0"


def synth(n: int = 1200, seed: int = 16) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pos = np.concatenate([
        np.column_stack([rng.uniform(-2, 2, n // 3), rng.uniform(-2, 2, n // 3), rng.normal(0, 0.002, n // 3)]),
        rng.normal([1.5, -1.0, 0.8], 0.2, (n // 3, 3)),
        rng.normal([-3.0, 2.5, 1.5], 0.05, (n - 2 * (n // 3), 3)),
    ])
    logs = rng.uniform(np.log(1e-3), np.log(0.3), (n, 1)) + rng.normal(0, 0.2, (n, 3))
    kind = rng.integers(0, 3, n)
    logs[kind == 1, 2] -= np.log(80.0)  # discs
    logs[kind == 2, 1:] -= np.log(40.0)  # needles
    logs[: n // 3, 2] = np.log(1e-3)  # the floor: flat discs
    logs[:2, 0] = 7.0  # above spz's top log-scale code (5.94)
    q = rng.normal(size=(n, 4))
    q[: n // 10, 0] = rng.normal(0, 1e-3, n // 10)  # w ~ 0
    q *= rng.uniform(0.3, 2.0, (n, 1))  # not normalised, as trainers save them
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    v = np.empty(n, [(a, "<f4") for a in names])
    for i, a in enumerate("xyz"):
        v[a] = pos[:, i]
    for i in range(3):
        v[f"f_dc_{i}"] = rng.normal(0, 1, n)
        v[f"scale_{i}"] = logs[:, i]
    for i in range(4):
        v[f"rot_{i}"] = q[:, i]
    v["opacity"] = rng.normal(1, 2, n)
    return v


def main() -> int:
    tool = shlex.split(sys.argv[1]) if len(sys.argv) > 1 else ["npx", "-y", f"@playcanvas/splat-transform@{VERSION}"]
    OUT.mkdir(parents=True, exist_ok=True)
    src = OUT / "synth.ply"
    PlyData([PlyElement.describe(synth(), "vertex")], byte_order="<").write(str(src))
    for out, extra in (("synth.compressed.ply", []), ("synth.spz", []), ("synth.v3.spz", ["--spz-version", "3"])):
        cmd = [*tool, "-w", "--no-tty", str(src), str(OUT / out), *extra]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
