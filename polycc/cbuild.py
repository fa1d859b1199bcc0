"""Race-safe cffi (API mode) builds of C shipped with polycc, cached in the build cache.

:func:`build_cffi` builds an extension once per hash of (sources, cdef, glue source, flags, cffi and
Python versions) under :func:`polycc.resources.cache_dir` ``("cffi")``, in a private temporary
directory moved into place with ``os.replace``, so concurrent pytest workers never see a
half-written module.  Used by the kernel and app host builds (:mod:`polycc.sim`) and the grid
search of :mod:`polycc.plan`.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import shutil
import sys
import sysconfig
import tempfile
from pathlib import Path

from polycc import resources
from polycc.errors import PolyccError


def source_hash(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(len(p).to_bytes(8, "little"))
        h.update(p)
    return h.hexdigest()[:16]


def build_cffi(prefix: str, cdef: str, source: str, sources: list[Path], include_dirs: list[Path],
               cflags: list[str], key_parts: list[bytes] = (), prepare=None, explain=None):
    """Build (once) and import a cffi API-mode extension; safe under concurrent pytest workers.

    The module name is ``<prefix>_<hash>``, the hash covering the sources, ``key_parts``, cdef,
    glue source, flags, cffi and Python versions; it is built in a private temporary directory
    under the build cache's ``cffi/`` and moved into place with ``os.replace``.  ``prepare(tmpdir)`` may
    write extra inputs (for instance a generated header) before compiling and returns extra
    include directories; ``explain(exc, extra_include_dirs)`` may turn a failed compile into
    the user's error message."""
    import cffi

    files = b"".join(p.name.encode() + p.read_bytes() for p in sources)
    key = source_hash(files, *key_parts, cdef.encode(), source.encode(), " ".join(cflags).encode(),
                      cffi.__version__.encode(), sys.version.encode())
    name = f"{prefix}_{key}"
    out_dir = resources.cache_dir("cffi")
    suffix = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
    target = out_dir / f"{name}{suffix}"
    if not target.exists():
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f"{name}-", dir=out_dir))
        try:
            extra = list(prepare(tmp)) if prepare else []
            ffi = cffi.FFI()
            ffi.cdef(cdef)
            ffi.set_source(name, source, sources=[str(p) for p in sources if p.suffix == ".c"],
                           include_dirs=[str(d) for d in [*include_dirs, *extra]], extra_compile_args=cflags)
            try:
                built = Path(ffi.compile(tmpdir=str(tmp), verbose=False))
            except Exception as exc:  # compiler missing or a warning under -Werror
                if explain is not None:
                    raise PolyccError(explain(exc, extra)) from None
                raise PolyccError(f"building {prefix} for the host failed ({exc}); install gcc and "
                                  "python3-dev") from None
            os.replace(built, target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    spec = importlib.util.spec_from_file_location(name, target,
                                                  loader=importlib.machinery.ExtensionFileLoader(name, str(target)))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
