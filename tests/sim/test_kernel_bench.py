"""Smoke run of the cycle benchmark (bench/bench_kernel.py): it builds, emulates both kernels,
checks the emulated results against the reference and writes its JSON."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from polycc.testing.bitexact import arm_or_skip
from polycc.testing.files import CHECKOUT


@pytest.mark.slow
@pytest.mark.arm
def test_bench_quick(tmp_path):
    arm_or_skip()
    pytest.importorskip("unicorn")
    pytest.importorskip("capstone")
    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, str(CHECKOUT / "bench" / "bench_kernel.py"), "--quick", "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    res = json.loads(out.read_text())
    rows = {r["scene"]: r for r in res["rows"]}
    assert set(rows) == {"room10", "room30", "room50", "room100", "room150", "planes3720", "fill64k", "vox150"}
    assert res["stack_bytes"] <= 512
    for name in ("room30", "room50", "room100", "room150", "fill64k"):
        assert rows[name]["speedup_typical"][0] >= 10, name
    assert rows["fill64k"]["flash_bytes"] <= 65536 and rows["fill64k"]["n_planes"] >= 8000
    assert rows["vox150"]["bytes_per_plane"] <= 8.0
