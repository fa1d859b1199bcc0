"""N independent copies of the host-built app (one ``polytopes.h``): the cffi module keeps the app's
state in C statics, so each drone loads its own copy of the shared object (a file copy in the build
cache, ``swarm/``; ``dlopen`` of distinct files gives distinct statics).  One process, no IPC: a copy
costs one file of ~100 KB and its load time (bench/bench_swarm.py measures both against one process
per drone)."""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import shutil
from pathlib import Path

from polycc import resources
from polycc.sim.app_ffi import AppSim


def _copy_module(mod, index: int):
    src = Path(mod.__file__)
    name = mod.__name__
    key = hashlib.sha256(src.read_bytes()).hexdigest()[:16]
    d = resources.cache_dir("swarm") / f"{key}_{index}"
    target = d / src.name
    if not target.exists():
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{src.name}.{os.getpid()}.tmp"
        shutil.copyfile(src, tmp)
        os.replace(tmp, target)
    spec = importlib.util.spec_from_file_location(name, target,
                                                  loader=importlib.machinery.ExtensionFileLoader(name, str(target)))
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m


class DroneApp(AppSim):
    """An :class:`AppSim` whose C statics are its own (instance ``index`` of the shared build)."""

    def __init__(self, header_path, index: int, defines: dict[str, str] | None = None):
        super().__init__(header_path, defines)  # builds (once) and loads the shared module
        if index > 0:
            self.mod = _copy_module(self.mod, index)
            self.lib, self.ffi = self.mod.lib, self.mod.ffi
            self._entry = self.ffi.new("shim_toc_entry_t *")
            self._rec = self.ffi.new("shim_commander_record_t *")
            self._log_index = {e.full_name: e.index for e in self.log_toc()}
            self._param_index = {e.full_name: e.index for e in self.param_toc()}


def drone_apps(header_path, n: int, defines: dict[str, str] | None = None) -> list[DroneApp]:
    """``n`` app instances with independent state (instance 0 is the shared module itself)."""
    return [DroneApp(header_path, i, defines) for i in range(n)]
