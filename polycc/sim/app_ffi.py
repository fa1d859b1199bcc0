"""cffi (API mode) build of the whole Crazyflie app for the host: ``polycc_app.c`` + kernel +
firmware API shims (``polycc/sim/shims/``) + one generated ``polytopes.h``.

The very ``.c`` files the firmware compiles, with the firmware's warning flags
(``-std=gnu11 -Wall -Wdouble-promotion -Werror``) plus ``-Wextra``, ``-ffp-contract=off`` and
``-fno-math-errno``; ``POLYCC_SHIM_HOST`` makes the shims' ``LOG_GROUP``/``PARAM_GROUP`` macros
register their tables at load time.

One extension per (sources, header, flags, cffi, Python) hash under ``build/cffi/``, built in a
private temporary directory and moved into place with ``os.replace`` (safe under pytest -n).

Python API (the simulated Crazyflie builds its cflib TOCs from it)::

    app = AppSim("out/polytopes.h")      # or the folder; AppSim(h, {"POLYCC_APP_BRAKE_ACC": "0.0f"}) for -D overrides
    app.reset()                          # shim_reset() + polycc_app_init(), as at boot
    app.log_toc()   -> [TocEntry(index, group, name, type, extended_type, address, size, has_callback)]
    app.param_toc() -> the same for parameters
    app.get_log("polycc", "psi"); app.get_param("polycc", "vmax"); app.set_param("polycc", "enable", 1)
    app.set_estimate(x, v); app.tick(tick_ms, usec, section_us) -> next period (ticks)
    app.commander() -> CommanderRecord;  app.trace() -> the last kernel call (inputs and output)

``TocEntry.type`` is the firmware's raw type byte (``LOG_FLOAT = 7`` ... with ``LOG_CORE 0x20``;
``PARAM_FLOAT = 0x06``, ``PARAM_UINT8 = 0x08`` ... with ``PARAM_CORE``/``PARAM_RONLY`` bits), index
order is groups by name then declaration order, and log indices are the ``logVarId_t`` values.
The same tables are reachable in C through ``polycc/sim/shims/polycc_shim.h``
(``shim_log_count``/``shim_log_entry``/``shim_log_value``, ``shim_param_count``/
``shim_param_entry``/``shim_param_index``/``shim_param_value``/``shim_param_set``).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from polycc import resources
from polycc.errors import PolyccError
from polycc.onboard.app import STATUS_NAMES  # noqa: F401 - re-exported for the simulator's users
from polycc.sim.cdef import headers_cdef
from polycc.sim.kernel_ffi import build_cffi

SRC = resources.firmware_src()
SHIMS = resources.shims()
APP_SOURCES = [SRC / "polycc_app.c", SRC / "polycc_kernel.c", SRC / "polycc_shield.c", SRC / "polycc_controller.c",
               SRC / "polycc_swarm.c"]
SHIM_SOURCES = sorted(SHIMS.glob("sim_*.c"))
HEADERS = [SRC / "polycc_app.h", SRC / "polycc_kernel.h", SRC / "polycc_scene_layout.h", SRC / "polycc_shield.h",
           SRC / "polycc_controller.h", SRC / "polycc_swarm.h"] + sorted(SHIMS.glob("*.h"))
# The firmware's flags that matter for code generation and warnings (tools/kbuild/Makefile.kbuild:
# -std=gnu11 -Wall -Wdouble-promotion, -Os -Werror in release, -fno-math-errno), the kernel's
# -ffp-contract=off, plus -Wextra on the host.
FIRMWARE_WARN_FLAGS = ["-std=gnu11", "-Wall", "-Wdouble-promotion", "-Werror", "-fno-math-errno", "-ffp-contract=off"]
HOST_CFLAGS = ["-O2", *FIRMWARE_WARN_FLAGS, "-Wextra", "-DPOLYCC_SHIM_HOST=1"]


# The shims' C API, the kernel's and the app's types and constants, all from their headers; then
# the constants of the generated header and the host-only glue below.
# The firmware types the controller API passes on (opaque here, as in the shims).
_OPAQUE = ("typedef struct state_s state_t;\ntypedef struct control_s control_t;\n"
           "typedef struct sensorData_s sensorData_t;\ntypedef uint32_t stabilizerStep_t;\n"
           "typedef struct setpoint_s setpoint_t;\n")
CDEF = headers_cdef(SHIMS / "polycc_shim.h", SRC / "polycc_scene_layout.h", SRC / "polycc_kernel.h",
                    SRC / "polycc_app.h", SRC / "polycc_shield.h", SRC / "polycc_controller.h") + _OPAQUE + \
    headers_cdef(
    SHIMS / "crtp_commander_high_level.h", SHIMS / "supervisor.h", SHIMS / "controller.h", SHIMS / "crtp.h") + """
float polycc_host_brake_acc(void);
#define POLYCC_SCENE_N_POLYS ...
#define POLYCC_SCENE_N_PLANES ...
#define POLYCC_HEADER_FORMAT ...
float polycc_host_scene_kappa(void);
const void *polycc_host_scene_array(int which, uint32_t *count);
float polycc_host_scene_const(int which);
"""

# Host-only glue: the scene constants of the header the app was built with.
GLUE = """
#include "polycc_shim.h"
#include "controller.h"
#include "crtp.h"
#include "crtp_commander_high_level.h"
#include "supervisor.h"
#include "polycc_app.h"
#include "polycc_controller.h"
#include "polycc_scene_layout.h"
#include "polytopes.h"
float polycc_host_scene_kappa(void) { return POLYCC_SCENE_KAPPA; }
float polycc_host_brake_acc(void) { return POLYCC_APP_BRAKE_ACC; }
/* The header's arrays as the app reads them: 0 planes, 1 polys, 2 clusters, 3 normals. */
const void *polycc_host_scene_array(int which, uint32_t *count)
{
    switch (which) {
    case 0: *count = polycc_scene.n_planes; return polycc_scene.planes;
    case 1: *count = polycc_scene.n_polys; return polycc_scene.polys;
    case 2: *count = polycc_scene.n_clusters; return polycc_scene.clusters;
    case 3: *count = polycc_scene.n_normals; return polycc_scene.normals;
    default: *count = 0; return 0;
    }
}
float polycc_host_scene_const(int which)
{
    return which == 0 ? polycc_scene.coord_bound : which == 1 ? polycc_scene.log_lmax : polycc_scene.quantum;
}
"""


def _first_error(scene_dir: Path, cflags: list[str]) -> str | None:
    """The compiler's first error line for the app with this scene, if a C compiler is on PATH."""
    import subprocess

    cc = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if cc is None:
        return None
    r = subprocess.run([cc, *cflags, f"-I{SHIMS}", f"-I{SRC}", f"-I{scene_dir}", "-fsyntax-only",
                        str(SRC / "polycc_app.c")], capture_output=True, text=True)
    lines = [ln for ln in r.stderr.splitlines() if "error" in ln]
    return lines[0].strip() if lines else None


@lru_cache(maxsize=16)
def _load(header_text: bytes, header_dir: str, defines: tuple[str, ...] = ()):
    cflags = HOST_CFLAGS + [f"-D{d}" for d in defines]

    def prepare(tmp: Path) -> list[Path]:
        inc = tmp / "scene"
        inc.mkdir()
        (inc / "polytopes.h").write_bytes(header_text)
        return [inc]

    def explain(exc: Exception, extra: list[Path]) -> str:
        why = (_first_error(extra[0], cflags) if extra else None) or str(exc)
        return (f"building the host app with {header_dir}/polytopes.h failed: {why}; check the header was written "
                "by this polycc's `polycc build` and that gcc and python3-dev are installed")

    return build_cffi("_polycc_app", CDEF, GLUE, APP_SOURCES + SHIM_SOURCES + HEADERS, [SHIMS, SRC], cflags,
                      key_parts=[header_text], prepare=prepare, explain=explain)


def load(header_path: str | Path, defines: dict[str, str] | None = None):
    """Build (if needed) and import the app extension for this ``polytopes.h``; ``defines``
    are extra ``-DNAME=VALUE`` (e.g. ``{"POLYCC_APP_BRAKE_S": "0.0f"}``)."""
    p = Path(header_path)
    if p.is_dir():
        p = p / "polytopes.h"
    if not p.is_file():
        raise PolyccError(f"{p}: no such scene header; run `polycc build` to write it")
    d = tuple(sorted(f"{k}={v}" for k, v in (defines or {}).items()))
    return _load(p.read_bytes(), str(p.parent), d)


@dataclass(frozen=True)
class TocEntry:
    """One log variable or parameter of the host build, as its firmware table declares it."""

    index: int  # logVarId_t for logs; the shim's param index for params
    group: str
    name: str
    type: int  # the firmware's raw type byte (LOG_* | LOG_CORE..., or PARAM_* bits)
    extended_type: int  # params: extended type byte (1 = PARAM_PERSISTENT); logs: 0
    address: int  # host address of the variable
    size: int  # bytes
    has_callback: bool

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"


@dataclass(frozen=True)
class CommanderRecord:
    count: int
    rejected: int
    relax_count: int
    tick: int
    priority: int
    active_priority: int
    modes: tuple[int, int, int, int, int, int]  # x, y, z, roll, pitch, yaw (stab_mode_t)
    velocity_body: bool
    velocity: tuple[float, float, float]  # m/s, float32 values
    velocity_bits: tuple[int, int, int]  # uint32 patterns of the float32 velocity
    yaw_rate: float
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m (position setpoints)
    hl_state: int = 0  # high-level planner: 0 idle (stopped), 1 flying, 2 landing
    hl_gotos: int = 0  # crtpCommanderHighLevelGoTo calls
    hl_lands: int = 0


class AppSim:
    """The app compiled for the host against one scene header; all state lives in the C module."""

    MODE_VELOCITY = 2  # stab_mode_t modeVelocity

    def __init__(self, header_path: str | Path, defines: dict[str, str] | None = None):
        p = Path(header_path)
        self.header_path = p / "polytopes.h" if p.is_dir() else p
        self.mod = load(self.header_path, defines)
        self.lib, self.ffi = self.mod.lib, self.mod.ffi
        self._entry = self.ffi.new("shim_toc_entry_t *")
        self._rec = self.ffi.new("shim_commander_record_t *")
        self._log_index = {e.full_name: e.index for e in self.log_toc()}
        self._param_index = {e.full_name: e.index for e in self.param_toc()}

    # ---------------------------------------------------------------- scene constants
    @property
    def kappa(self) -> float:
        return float(self.lib.polycc_host_scene_kappa())

    @property
    def brake_acc(self) -> float:
        """POLYCC_APP_BRAKE_ACC of this build, m/s^2 (0: braking term compiled out)."""
        return float(self.lib.polycc_host_brake_acc())

    @property
    def n_polys(self) -> int:
        return int(self.lib.POLYCC_SCENE_N_POLYS)

    def packed_scene(self):
        """The scene exactly as the app reads it (copies of the header's arrays), as a PackedScene
        for the Python reference."""
        import numpy as np

        from polycc.onboard.layout import CLUSTER_DTYPE, NORMAL_DTYPE, PLANE_DTYPE, POLY_DTYPE, PackedScene

        cnt = self.ffi.new("uint32_t *")

        def array(which, dtype):
            ptr = self.lib.polycc_host_scene_array(which, cnt)
            if ptr == self.ffi.NULL or cnt[0] == 0:
                return np.zeros(0, dtype)
            return np.frombuffer(self.ffi.buffer(ptr, cnt[0] * dtype.itemsize), dtype).copy()

        const = self.lib.polycc_host_scene_const
        return PackedScene(normals=array(3, NORMAL_DTYPE), planes=array(0, PLANE_DTYPE),
                           polys_raw=array(1, POLY_DTYPE), clusters=array(2, CLUSTER_DTYPE),
                           quantum=np.float32(const(2)), coord_bound=np.float32(const(0)),
                           log_lmax=np.float32(const(1)))

    # ---------------------------------------------------------------- TOCs
    def _toc(self, count, getter, size_fn) -> list[TocEntry]:
        out = []
        ffi, e = self.ffi, self._entry
        for i in range(count()):
            if getter(i, e) != 0:
                break
            out.append(TocEntry(i, ffi.string(e.group).decode(), ffi.string(e.name).decode(), int(e.type),
                                int(e.extended_type), int(ffi.cast("uintptr_t", e.address)), int(size_fn(e.type)),
                                e.callback != ffi.NULL))
        return out

    def log_toc(self) -> list[TocEntry]:
        """Every log variable (the app's groups and the simulated stateEstimate/kalman groups)."""
        return self._toc(self.lib.shim_log_count, self.lib.shim_log_entry, self.lib.shim_log_type_size)

    def param_toc(self) -> list[TocEntry]:
        return self._toc(self.lib.shim_param_count, self.lib.shim_param_entry, self.lib.shim_param_type_size)

    def get_log(self, group: str, name: str) -> float:
        return float(self.lib.shim_log_value(self._log_index[f"{group}.{name}"]))

    def get_param(self, group: str, name: str) -> float:
        return float(self.lib.shim_param_value(self._param_index[f"{group}.{name}"]))

    def set_param(self, group: str, name: str, value: float) -> None:
        key = f"{group}.{name}"
        if key not in self._param_index:
            raise PolyccError(f"no parameter {key}; the app has {', '.join(sorted(self._param_index))}")
        if self.lib.shim_param_set(self._param_index[key], float(value)) != 0:
            raise PolyccError(f"parameter {key} is read-only")

    # ---------------------------------------------------------------- simulation
    def reset(self) -> None:
        """Fresh clock, commander and estimate, then the app's own init (as at boot)."""
        self.lib.shim_reset()
        self.lib.polycc_app_init()

    def set_estimate(self, x, v=(0.0, 0.0, 0.0)) -> None:
        self.lib.shim_set_estimate(float(x[0]), float(x[1]), float(x[2]), float(v[0]), float(v[1]), float(v[2]))

    def set_position_variance(self, var) -> None:
        self.lib.shim_set_position_variance(float(var[0]), float(var[1]), float(var[2]))

    def tick(self, tick_ms: int, usec: int = 0, section_us: int = 0) -> int:
        """Runs one app tick at FreeRTOS tick ``tick_ms``; returns the app's next period in ticks."""
        self.lib.shim_set_tick(int(tick_ms) & 0xFFFFFFFF)
        self.lib.shim_set_usec(int(usec), int(section_us))
        return int(self.lib.polycc_app_tick())

    def commander(self) -> CommanderRecord:
        r = self._rec
        self.lib.shim_commander_get(r)
        import numpy as np

        v = np.array([r.vx, r.vy, r.vz], np.float32)
        return CommanderRecord(int(r.count), int(r.rejected), int(r.relax_count), int(r.tick), int(r.priority),
                               int(r.active_priority),
                               (r.mode_x, r.mode_y, r.mode_z, r.mode_roll, r.mode_pitch, r.mode_yaw),
                               bool(r.velocity_body), tuple(float(a) for a in v),
                               tuple(int(b) for b in v.view(np.uint32)), float(r.yaw_rate),
                               (float(r.px), float(r.py), float(r.pz)), int(r.hl_state), int(r.hl_gotos),
                               int(r.hl_lands))

    def airborne(self, x=(0.0, 0.0, 1.0)) -> None:
        """As after a finished high-level takeoff: hovering at ``x`` under the high-level commander,
        so the app may take control (the supervisor reports flying)."""
        self.lib.shim_hl_hover_at(float(x[0]), float(x[1]), float(x[2]))
        self.lib.shim_set_attitude(0.0, 0.0, 0.0, 36000.0)

    def trace(self):
        """The app's last kernel call (``polycc_app_trace_t``: calls, x, goal, params, out)."""
        return self.lib.polycc_app_trace()

    def debug_output(self) -> str:
        buf = self.ffi.new("char[]", 8192)
        n = self.lib.shim_debug_read(buf, 8192)
        return self.ffi.string(buf, n).decode(errors="replace")
