"""Cost of reading scenes with outward quantization bounds: time, peak memory and ellipsoid volume, as ratios
to the baseline read (the bare decode, no inflation) measured side by side in one run. Prints a table, writes
bench/results/bench_ingest.json.

Scenes: plant.splat (8-bit quaternions, 113,648 splats) and, when splat-transform is installed
(POLYCC_SPLAT_TRANSFORM or on PATH), donut_fused.ply converted to .compressed.ply and .spz.

    python bench/bench_ingest.py
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from common import print_table, write_json

from polycc.scene import load as load_mod
from polycc.scene.load import SceneOptions, load_scene
from polycc.scene.readers import read_splats
from polycc.testing.files import SCENES


def _timed(fn, repeat=3):
    best, peak = 1e9, 0
    for _ in range(repeat):
        tracemalloc.start()
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
        peak = max(peak, tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    return out, best, peak / 2**20


def _bare(path):
    raw = read_splats(path)
    raw.bounds = None
    orig = load_mod.read_splats
    load_mod.read_splats = lambda p: raw
    try:
        return load_scene(path, SceneOptions(drop_invalid=True))
    finally:
        load_mod.read_splats = orig


def main() -> int:
    files = [("plant.splat", SCENES / "plant.splat")]
    tmp = Path(tempfile.mkdtemp(prefix="polycc-bench-ingest-"))
    st = os.environ.get("POLYCC_SPLAT_TRANSFORM") or shutil.which("splat-transform")
    if st:
        for ext in ("compressed.ply", "spz"):
            out = tmp / f"donut_fused.{ext}"
            subprocess.run([st, "-w", "--no-tty", str(SCENES / "donut_fused.ply"), str(out)], check=True,
                           capture_output=True)
            files.append((f"donut_fused.{ext}", out))
    rows, res = [], []
    for name, path in files:
        base, tb, mb = _timed(lambda: _bare(path))
        infl, ti, mi = _timed(lambda: load_scene(path, SceneOptions(drop_invalid=True)))
        vol = np.prod(infl.ellipsoids.sigmas, axis=1) / np.prod(base.ellipsoids.sigmas, axis=1)
        r = {"file": name, "splats": len(infl.ellipsoids), "bare_s": tb, "inflated_s": ti, "time_ratio": ti / tb,
             "bare_peak_mb": mb, "inflated_peak_mb": mi, "memory_ratio": mi / mb,
             "volume_factor_median": float(np.median(vol)), "volume_factor_p95": float(np.percentile(vol, 95))}
        res.append(r)
        rows.append([name, r["splats"], tb, ti, r["time_ratio"], mb, mi, r["memory_ratio"],
                     r["volume_factor_median"], r["volume_factor_p95"]])
    shutil.rmtree(tmp, ignore_errors=True)
    print_table("reading with outward quantization bounds vs the bare decode (same run; k = 1)",
                ["file", "splats", "bare s", "inflated s", "time ratio", "bare MiB", "inflated MiB", "memory ratio",
                 "volume x median", "volume x p95"], rows)
    write_json("bench_ingest", {"results": res})
    return 0


if __name__ == "__main__":
    sys.exit(main())
