"""Cortex-M4 (qemu -M netduinoplus2, semihosting) runs of ``polycc_swarm_step``, built with the
firmware's ARM flags like :mod:`polycc.sim.kernel_arm`, for the bit-exactness tests."""

from __future__ import annotations

import subprocess
import tempfile
from pathlib import Path

import numpy as np

from polycc.errors import PolyccError
from polycc.onboard.barrier import Params
from polycc.onboard.layout import PackedScene
from polycc.onboard.swarm import Swarm
from polycc.sim.kernel_arm import ARM_DIR, QEMU, SRC, build
from polycc.sim.kernel_ffi import OUT_DTYPE

NBR_BYTES = 32  # sizeof(polycc_nbr_t)


def table_bytes(sw: Swarm) -> bytes:
    """The ``polycc_swarm_t`` image of a reference table (little-endian, as the C lays it out)."""
    out = b""
    for nb in sw.slots:
        if nb is None:
            out += bytes(NBR_BYTES)
        else:
            out += (np.asarray(nb.n, np.float32).tobytes() + np.array([nb.a, nb.b, nb.r], np.float32).tobytes()
                    + np.uint32(nb.age_ms).tobytes() + bytes([nb.id & 0xFF, 1, 0, 0]))
    return out + np.uint32(sw.count).tobytes()


def test_program() -> Path:
    srcs = [ARM_DIR / "swarm_main.c", SRC / "polycc_swarm.c", ARM_DIR / "startup.c", ARM_DIR / "semihost.c"]
    heads = [ARM_DIR / "semihost.h", ARM_DIR / "scene_image.h", SRC / "polycc_swarm.h"]
    return build("swarm_test", srcs, extra_headers=heads) / "swarm_test.elf"


def run_qemu(elf: Path, scene: PackedScene, params: Params, v_nbr: float, cases, timeout: float = 600.0):
    """``cases``: [(x (3,), goal (3,), Swarm)]; returns OUT_DTYPE records from the ARM build."""
    with tempfile.TemporaryDirectory(prefix="polycc-qemu-swarm-") as d:
        d = Path(d)
        (d / "scene.bin").write_bytes(scene.to_bytes())
        blob = [np.array(params.f32(), np.float32).tobytes(), np.float32(v_nbr).tobytes(),
                np.uint32(len(cases)).tobytes()]
        for x, goal, sw in cases:
            blob.append(np.r_[np.asarray(x, np.float32), np.asarray(goal, np.float32)].astype(np.float32).tobytes())
            blob.append(table_bytes(sw))
        (d / "states.bin").write_bytes(b"".join(blob))
        cmd = [QEMU, "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-serial", "none",
               "-semihosting-config", "enable=on,target=native", "-kernel", str(elf)]
        r = subprocess.run(cmd, cwd=d, capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0:
            raise PolyccError(f"qemu run failed (exit {r.returncode}): {(r.stdout + r.stderr).strip()[:300]}")
        return np.frombuffer((d / "out.bin").read_bytes(), OUT_DTYPE).copy()
