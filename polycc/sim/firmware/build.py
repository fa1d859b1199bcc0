"""Build a native CrazySim SITL ``cf2`` with the polycc app and a scene header compiled in (cached).

The SITL fork (llanesc/crazyflie-firmware ``sitl-release``) builds ``cf2`` with its own CMake project,
``sitl_make/CMakeLists.txt``. It has no app layer: upstream's ``src/modules/src/app_handler.c`` (the
``APP`` FreeRTOS task that calls ``appMain()`` after ``systemWaitStart()``) is in the tree but not in the
source list, and ``system.c`` calls ``appInit()`` only under ``CONFIG_APP_ENABLE``.

How the app gets in, without writing to the tree (:func:`build_cf2`)
-------------------------------------------------------------------
Each cache entry holds

* ``overlay/``: symlinks to the tree's top-level entries plus a real ``overlay/sitl_make/`` with a
  generated wrapper ``CMakeLists.txt`` that ``include()``\\ s the fork's own, unmodified
  ``<tree>/sitl_make/CMakeLists.txt``. An included file runs in the wrapper's directory scope, so the
  fork's ``${CMAKE_CURRENT_SOURCE_DIR}/..`` is the overlay and its generated ``version.c`` lands there.
  Also a symlink to ``log_param_linker.ld``, an empty stand-in for ``cmake/sitl_gazebo.cmake`` (the
  Gazebo plugin's ExternalProject, not needed for a bare ``cf2``) and ``build_info.json`` (the
  firmware's release-version mechanism; a git checkout gets its ``.git`` linked instead);
* ``app/``: a copy of the app sources (``firmware_app/src``, :func:`polycc.resources.firmware_app`),
  any extra sources, and the scene header;
* a ``python -> python3`` shim on ``PATH`` (the fork hard-codes ``COMMAND python``).

After the ``include()`` the wrapper adds ``app_handler.c`` and the app's objects (``obj-y`` of
``firmware_app/src/Kbuild``) to ``cf2``, defines every ``CONFIG_*`` of the app's ``app-config`` (as the
firmware's Kconfig would: ``y`` -> 1) plus ``kconfig`` overrides (e.g. ``CONFIG_CONTROLLER_OOT``), and
gives the app files the ``ccflags-y`` of their Kbuild (``-ffp-contract=off -fno-math-errno``) and the
header. Why not ``-D`` on the fork's project: its ``version.c`` rule writes into the tree root and it has
no per-file flags; why not a patched copy: 34 MB per build and a patch to keep in sync.

SITL fixes (``fixes``, all on by default, ``()`` builds the fork as is; C in ``support/``):

* ``stabilizer-delay-until``: ``stabilizer.c`` passes a ``uint32_t *`` to
  ``vTaskDelayUntil(TickType_t *, ...)``, and ``TickType_t`` is 64-bit on the POSIX port; the high
  half is an uninitialised stack slot and, when it is not 0, the priority-5 stabilizer spins forever in
  its calibration wait and starves every other task (measured: 10 of 25 boots under load hung).
  ``stabilizer.c`` is compiled with ``-DvTaskDelayUntil=polycc_sitl_vTaskDelayUntil_u32``.
* ``deck-params``: the fork builds no deck subsystem, so its TOC lacks the ``deck`` group whose
  presence flags (``deck.bcZRanger``, ...) every real firmware has; cfclient's tabs raise KeyError on
  connect without them. The same read-only flags, all 0 (no deck attached).
* ``p2p``: the fork leaves ``radiolink.c`` out (no nRF), so an app using the radio's peer-to-peer
  broadcast (``p2pRegisterCB``, ``radiolinkSendP2PPacketBroadcast``; the polycc app's swarm relay) does
  not link. A broadcast leaves as a CRTP packet on an unused port, which the bridge hands to the other
  instances (``--air``), and one coming in reaches the registered callback. Required by the polycc app.
* ``debug-rx-drops`` (diagnostic, off): print every packet the socket link's 5-deep RX queue drops.

Next to ``cf2`` goes ``libpolycc_sitl_clock.so`` (``support/polycc_sitl_clock.c``, LD_PRELOAD): it lets
the bridge drive the FreeRTOS tick (:mod:`polycc.sim.firmware.bridge`).

Cache: ``<cache>/firmware/sitl/<key[:20]>/`` (:func:`polycc.resources.cache_dir`), ``key`` a SHA-256
over the tree's content (``src/``, ``vendor/FreeRTOS/``, ``sitl_make/``, ``tools/make/``), the app
files, the header, the Kconfig symbols, extra sources and flags, the fixes and support sources, the
compiler and CMake versions, and :data:`RECIPE_VERSION`. Builds run under a file lock; an entry is
complete only once ``cf2`` has been moved into it. Errors are one-line :class:`PolyccError` s: not a SITL
tree, no cmake/compiler, a failed configure or build (first error, the last lines of the compiler
output and the full log's path).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from polycc import resources
from polycc.errors import PolyccError
from polycc.firmware_trees import locked, resolve_tree, sha256_file, tree_identity

RECIPE_VERSION = "polycc-sitl-cf2/3"
IDENTITY_DIRS = ("src", "vendor/FreeRTOS", "sitl_make", "tools/make")
SUPPORT = Path(__file__).resolve().parent / "support"
FIXES_SOURCE = SUPPORT / "polycc_sitl_fixes.c"
CLOCK_SHIM_SOURCE = SUPPORT / "polycc_sitl_clock.c"
CLOCK_SHIM_NAME = "libpolycc_sitl_clock.so"

# fix name -> CMake lines appended to the wrapper (the C side is support/polycc_sitl_fixes.c)
SITL_FIXES = {
    "stabilizer-delay-until": (
        'set_property(SOURCE "${CF2_SITL_SRCS_DIR}/modules/src/stabilizer.c" APPEND PROPERTY\n'
        '  COMPILE_DEFINITIONS "vTaskDelayUntil=polycc_sitl_vTaskDelayUntil_u32")\n'),
    "debug-rx-drops": (
        'set_property(SOURCE "${CF2_SITL_SRCS_DIR}/hal/src/socketlink.c" APPEND PROPERTY\n'
        '  COMPILE_DEFINITIONS "xQueueGenericSend=polycc_sitl_dbg_xQueueGenericSend")\n'),
    "deck-params": (
        'set_property(SOURCE "${POLYCC_FIXES_SOURCE}" APPEND PROPERTY\n'
        '  COMPILE_DEFINITIONS "POLYCC_SITL_DECK_PARAMS")\n'),
    "p2p": (
        'set_property(SOURCE "${POLYCC_FIXES_SOURCE}" APPEND PROPERTY\n'
        '  COMPILE_DEFINITIONS "POLYCC_SITL_P2P")\n'),
}
DEFAULT_FIXES = ("deck-params", "stabilizer-delay-until", "p2p")

WRAPPER_CMAKE = r"""# Generated by polycc ({recipe}); do not edit.
# Reuses the CrazySim SITL fork's own CMake project unchanged and adds the app layer.
cmake_minimum_required(VERSION 3.11)
project(polycc_cf2_sitl C)

set(POLYCC_FW_TREE "{tree}")
set(POLYCC_SCENE "{header}")

# The fork's project, in this directory's scope: its ${{CMAKE_CURRENT_SOURCE_DIR}}/.. is the overlay.
include("${{POLYCC_FW_TREE}}/sitl_make/CMakeLists.txt")

# Upstream's app layer: app_handler.c creates the APP task (appMain after systemWaitStart);
# system.c calls appInit() when CONFIG_APP_ENABLE is defined.
set(POLYCC_APP_SOURCES {sources})
target_sources(cf2 PRIVATE "${{POLYCC_FW_TREE}}/src/modules/src/app_handler.c" ${{POLYCC_APP_SOURCES}})
# Kconfig symbols of the app's app-config (y -> 1) and the caller's overrides, as the firmware's
# Kconfig would define them in autoconf.h.
target_compile_definitions(cf2 PRIVATE {kconfig})
# The app's Kbuild flags (bit-exact kernel: no FMA contraction) and the scene header.
set_source_files_properties(${{POLYCC_APP_SOURCES}} PROPERTIES
  COMPILE_OPTIONS "{app_opts}"
  COMPILE_DEFINITIONS "POLYCC_SCENE_HEADER=\"${{POLYCC_SCENE}}\""
  INCLUDE_DIRECTORIES "{app_includes}")
{fixes}"""

GAZEBO_STUB = ("# Generated by polycc: stands in for the fork's cmake/sitl_gazebo.cmake (an ExternalProject\n"
               "# for the Gazebo plugin, not needed for a bare cf2).\n")


@dataclass
class Cf2Build:
    """A built (or cached) SITL firmware."""

    cf2: Path             # the executable
    clock_shim: Path      # libpolycc_sitl_clock.so (LD_PRELOAD; polycc.sim.firmware.sitl)
    key: str              # cache key (hex)
    cached: bool          # an existing build was reused
    seconds: float        # wall time of this call
    build_dir: Path       # the cache entry (build.log, build.json, overlay/, app/)
    tree: Path            # the SITL tree it was built from
    app_warnings: list[str] = field(default_factory=list)  # compiler warnings in the app's own files


# --------------------------------------------------------------------------- app
def read_kconfig(path: Path) -> dict[str, str]:
    """``CONFIG_*=value`` lines of a Kconfig fragment (``app-config``)."""
    out: dict[str, str] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            m = re.match(r"\s*(CONFIG_\w+)\s*=\s*(.*?)\s*$", line)
            if m:
                out[m.group(1)] = m.group(2)
    return out


def kbuild_objects(kbuild: Path) -> list[str]:
    """Source names (``.c``) of the ``obj-y += x.o`` lines of a Kbuild file."""
    names = []
    for line in kbuild.read_text().splitlines():
        m = re.match(r"\s*obj-y\s*\+?=\s*(.*)$", line)
        if m:
            names += [w[:-2] + ".c" for w in m.group(1).split() if w.endswith(".o")]
    return names


def kbuild_ccflags(kbuild: Path) -> list[str]:
    """The literal flags of ``ccflags-y`` lines (tokens with make variables are left to the wrapper)."""
    flags = []
    for line in kbuild.read_text().splitlines():
        m = re.match(r"\s*ccflags-y\s*\+?=\s*(.*)$", line)
        if m:
            flags += [w for w in m.group(1).split() if "$(" not in w and ")" not in w]
    return flags


def _kconfig_defines(cfg: dict[str, str]) -> list[str]:
    out = []
    for k, v in sorted(cfg.items()):
        v = str(v).strip()
        if v in ("n", ""):
            continue
        if v == "y":
            v = "1"
        elif not re.fullmatch(r"-?(0x[0-9a-fA-F]+|\d+)", v):
            v = '"' + v.strip('"').replace('"', '\\"') + '"'
        out.append(f"{k}={v}")
    return out


def header_path(header: str | os.PathLike) -> Path:
    """``polytopes.h`` itself or the build folder holding it, checked."""
    p = Path(header).expanduser()
    if p.is_dir():
        p = p / "polytopes.h"
    if not p.is_file():
        raise PolyccError(f"{p}: scene header not found; run `polycc build SCENE -o DIR` first")
    if b"POLYCC_HEADER_FORMAT" not in p.read_bytes()[:200_000]:
        raise PolyccError(f"{p}: not a polycc scene header (no POLYCC_HEADER_FORMAT); regenerate it with polycc build")
    return p.resolve()


# --------------------------------------------------------------------------- tools
def _first_line(cmd) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        return (out.stdout or out.stderr).splitlines()[0].strip()
    except (OSError, IndexError, subprocess.TimeoutExpired):
        return "?"


def tool_versions() -> dict:
    """cmake, the C compiler and python3 (part of the cache key), or a one-line error naming the install."""
    cmake = shutil.which("cmake")
    if not cmake:
        raise PolyccError("cmake not found on PATH; install cmake >= 3.11 (apt-get install cmake) to build the "
                          "SITL firmware")
    cc = shutil.which(os.environ.get("CC", "")) if os.environ.get("CC") else (shutil.which("cc") or
                                                                              shutil.which("gcc"))
    if not cc:
        raise PolyccError("no C compiler found (CC, cc or gcc); install gcc (apt-get install build-essential)")
    py3 = shutil.which("python3") or sys.executable
    return {"cmake": _first_line([cmake, "--version"]), "cmake_path": cmake, "cc": _first_line([cc, "--version"]),
            "cc_path": cc, "python3": py3}


def _first_error(log: str) -> str:
    pats = (r"^.*?:\d+:\d+: (?:fatal )?error: .*$", r"^.*?: undefined reference to .*$",
            r"^.*?collect2: error: .*$", r"^CMake Error.*$", r"^.*?: No such file or directory.*$",
            r"^.*\berror\b.*$")
    for pat in pats:
        m = re.search(pat, log, re.M | re.I)
        if m:
            line = m.group(0).strip()
            if pat.startswith("^CMake Error"):
                rest = log[m.end():].strip().splitlines()
                if rest:
                    line += " " + rest[0].strip()
            return line[:300]
    return ""


def _tail(log: str, n: int = 3) -> str:
    lines = [ln.strip() for ln in log.strip().splitlines() if ln.strip()]
    return " | ".join(ln[:160] for ln in lines[-n:]) or "(no output)"


def _app_warnings(log: str, app_dir: Path) -> list[str]:
    key = str(app_dir)
    return sorted({ln.strip() for ln in log.splitlines() if "warning:" in ln and key in ln})


# --------------------------------------------------------------------------- build
def _q(s) -> str:
    """CMake string literal content."""
    return str(s).replace("\\", "\\\\").replace('"', '\\"')


def _hash_dir_headers(d: Path) -> dict:
    return {p.relative_to(d).as_posix(): sha256_file(p) for p in sorted(d.rglob("*")) if p.is_file()} \
        if d.is_dir() else {}


def build_cf2(tree: str | os.PathLike, header: str | os.PathLike, *, app_dir: str | os.PathLike | None = None,
              extra_sources=(), include_dirs=(), kconfig: dict[str, str] | None = None, extra_cflags=(),
              fixes=DEFAULT_FIXES, jobs: int = 2, force: bool = False, log=None) -> Cf2Build:
    """Build (or reuse) a SITL ``cf2`` with the app and ``header`` compiled in.

    Parameters
    ----------
    tree : a CrazySim SITL tree folder, or its tarball (extracted once into the cache).
    header : ``polytopes.h`` of ``polycc build``, or its build folder.
    app_dir : the app (default: the ``firmware_app/`` polycc ships).
    extra_sources : more C files compiled into ``cf2`` with the app's flags (e.g. an out-of-tree controller).
    include_dirs : more include folders for the app files.
    kconfig : ``CONFIG_*`` symbols defined for the whole ``cf2`` (``"y"`` -> 1), over the app's ``app-config``.
    extra_cflags : more flags for the app files.
    fixes : names from :data:`SITL_FIXES` (default: :data:`DEFAULT_FIXES`; ``()`` builds the fork as is).
    log : callable for progress lines.

    Returns
    -------
    Cf2Build
    """
    t0 = time.monotonic()
    say = log or (lambda msg: None)
    tree = resolve_tree(tree, "sitl", say)
    header = header_path(header)
    app_dir = Path(app_dir).resolve() if app_dir is not None else resources.firmware_app()
    src = app_dir / "src"
    if not (src / "Kbuild").is_file() or not (src / "polycc_app.c").is_file():
        raise PolyccError(f"{app_dir}: not the polycc firmware_app (src/Kbuild or src/polycc_app.c missing)")
    sources = kbuild_objects(src / "Kbuild")
    missing = [s for s in sources if not (src / s).is_file()]
    if missing:
        raise PolyccError(f"{src / 'Kbuild'} lists {missing[0][:-2]}.o but {src / missing[0]} is missing")
    extra_sources = [Path(p).resolve() for p in extra_sources]
    for p in extra_sources:
        if not p.is_file():
            raise PolyccError(f"{p}: extra source not found")
    include_dirs = [Path(p).resolve() for p in include_dirs]
    cfg = read_kconfig(app_dir / "app-config")
    cfg.update({k: str(v) for k, v in (kconfig or {}).items()})
    cfg.setdefault("CONFIG_APP_ENABLE", "y")
    cfg.setdefault("CONFIG_APP_PRIORITY", "1")
    cfg.setdefault("CONFIG_APP_STACKSIZE", "350")
    if cfg["CONFIG_APP_ENABLE"] not in ("y", "1"):
        raise PolyccError(f"{app_dir / 'app-config'}: CONFIG_APP_ENABLE is not y; the app would never start")
    cflags = kbuild_ccflags(src / "Kbuild") + list(extra_cflags)
    fixes = tuple(sorted(set(fixes)))
    unknown = [f for f in fixes if f not in SITL_FIXES]
    if unknown:
        raise PolyccError(f"unknown SITL fix {unknown[0]!r}; known: {', '.join(SITL_FIXES)}")
    tools = tool_versions()
    parts = {
        "recipe": RECIPE_VERSION, "wrapper": hashlib.sha256(WRAPPER_CMAKE.encode()).hexdigest(),
        "tree": tree_identity(tree, IDENTITY_DIRS),
        "app": {p.name: sha256_file(p) for p in sorted(src.iterdir()) if p.is_file()},
        "app_config": sha256_file(app_dir / "app-config") if (app_dir / "app-config").is_file() else None,
        "kconfig": cfg, "header": sha256_file(header), "cflags": cflags,
        "extra": [(p.name, sha256_file(p)) for p in extra_sources],
        "include_dirs": [(str(d), _hash_dir_headers(d)) for d in include_dirs],
        "tools": {k: v for k, v in tools.items() if k in ("cmake", "cc")},
        "fixes": [(f, SITL_FIXES[f]) for f in fixes], "fixes_src": sha256_file(FIXES_SOURCE),
        "clock_shim": sha256_file(CLOCK_SHIM_SOURCE),
    }
    key = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()
    root = resources.cache_dir("firmware", "sitl")
    entry = root / key[:20]
    cf2 = entry / "cf2"
    with locked(root / f".{key[:20]}.lock"):
        if cf2.is_file() and os.access(cf2, os.X_OK) and not force:
            meta = json.loads((entry / "build.json").read_text()) if (entry / "build.json").is_file() else {}
            return Cf2Build(cf2, entry / CLOCK_SHIM_NAME, key, True, time.monotonic() - t0, entry, tree,
                            meta.get("app_warnings", []))
        # built in place under the lock, so the paths compiled into cf2 stay valid
        if entry.exists():
            shutil.rmtree(entry)
        entry.mkdir(parents=True)
        try:
            warnings = _build(entry, tree, app_dir, sources, header, extra_sources, include_dirs, cfg, cflags,
                              fixes, tools, jobs, key, say)
            (entry / "build.json").write_text(json.dumps({
                "key": key, "tree": str(tree), "app": str(app_dir), "header": str(header), "kconfig": cfg,
                "cflags": cflags, "extra_sources": [str(p) for p in extra_sources], "fixes": list(fixes),
                "tools": tools, "recipe": RECIPE_VERSION, "app_warnings": warnings,
                "built": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=2) + "\n")
            os.replace(entry / "build" / "cf2", cf2)  # marks the entry complete
        except BaseException:
            shutil.rmtree(entry, ignore_errors=True)
            raise
    return Cf2Build(cf2, entry / CLOCK_SHIM_NAME, key, False, time.monotonic() - t0, entry, tree, warnings)


def _build(entry: Path, tree: Path, app_dir: Path, sources: list[str], header: Path, extra_sources: list[Path],
           include_dirs: list[Path], cfg: dict, cflags: list[str], fixes: tuple, tools: dict, jobs: int, key: str,
           say) -> list[str]:
    overlay = entry / "overlay"
    overlay.mkdir()
    for e in sorted(tree.iterdir()):
        if e.name not in ("sitl_make", "version.c", "build_info.json"):
            os.symlink(e, overlay / e.name)
    sm = overlay / "sitl_make"
    (sm / "cmake").mkdir(parents=True)
    os.symlink(tree / "sitl_make" / "log_param_linker.ld", sm / "log_param_linker.ld")
    (sm / "cmake" / "sitl_gazebo.cmake").write_text(GAZEBO_STUB)
    if not (tree / ".git").exists():
        m = re.search(r"-([0-9a-f]{7,40})$", tree.name)
        (overlay / "build_info.json").write_text(json.dumps({"tag": m.group(1) if m else "sitl"}) + "\n")
    app = entry / "app"
    (app / "src").mkdir(parents=True)
    for p in sorted((app_dir / "src").iterdir()):
        if p.is_file() and p.suffix in (".c", ".h"):
            shutil.copy2(p, app / "src" / p.name)
    (app / "extra").mkdir()
    copied = []
    for p in extra_sources:
        dst = app / "extra" / p.name
        if dst.exists():
            raise PolyccError(f"two extra sources named {p.name}; rename one")
        shutil.copy2(p, dst)
        copied.append(dst)
    scene = app / "scene" / "polytopes.h"
    scene.parent.mkdir()
    shutil.copy2(header, scene)
    fixes_cmake = ""
    if fixes:
        shutil.copy2(FIXES_SOURCE, app / FIXES_SOURCE.name)
        fixes_cmake = (f"\n# SITL fork work-arounds ({', '.join(fixes)}): see {FIXES_SOURCE.name}\n"
                       f'set(POLYCC_FIXES_SOURCE "{_q(app / FIXES_SOURCE.name)}")\n'
                       f'target_sources(cf2 PRIVATE "${{POLYCC_FIXES_SOURCE}}")\n'
                       + "".join(SITL_FIXES[f] for f in fixes))
    srcs = [app / "src" / s for s in sources] + copied
    (sm / "CMakeLists.txt").write_text(WRAPPER_CMAKE.format(
        recipe=RECIPE_VERSION, tree=_q(tree), header=_q(scene),
        sources=" ".join(f'"{_q(s)}"' for s in srcs),
        kconfig=" ".join(f'"{_q(d)}"' for d in _kconfig_defines(cfg)),
        app_opts=_q(";".join(cflags)), app_includes=_q(";".join(str(d) for d in [app / "src", *include_dirs])),
        fixes=fixes_cmake))
    shim = entry / "pyshim"
    shim.mkdir()
    os.symlink(tools["python3"], shim / "python")
    env = dict(os.environ, PATH=f"{shim}{os.pathsep}{os.environ.get('PATH', '')}")
    bdir = entry / "build"
    logf = entry / "build.log"
    steps = [
        ("configure", [tools["cmake_path"], "-S", str(sm), "-B", str(bdir), "-DCMAKE_BUILD_TYPE=Release", "-Wno-dev",
                       f"-DCMAKE_C_COMPILER={tools['cc_path']}"]),
        ("build", [tools["cmake_path"], "--build", str(bdir), "--target", "cf2", "--", f"-j{max(1, int(jobs))}"]),
    ]
    full = ""
    with open(logf, "w") as lf:
        for what, cmd in steps:
            say(f"{'configuring' if what == 'configure' else 'compiling'} the SITL firmware ({tree.name})")
            lf.write("$ " + " ".join(cmd) + "\n")
            lf.flush()
            r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=entry)
            lf.write(r.stdout)
            full += r.stdout
            if r.returncode != 0:
                lf.flush()
                failed = entry.parent / f"failed-{key[:20]}.log"
                shutil.copy(logf, failed)
                first = _first_error(r.stdout)
                raise PolyccError(f"SITL firmware {what} failed: {first + ' ... ' if first else ''}"
                                  f"last lines: {_tail(r.stdout)} (full log: {failed})")
    if not (bdir / "cf2").is_file():
        raise PolyccError(f"the SITL build produced no cf2 (see {logf})")
    cmd = [tools["cc_path"], "-O2", "-Wall", "-fPIC", "-shared", "-o", str(entry / CLOCK_SHIM_NAME),
           str(CLOCK_SHIM_SOURCE), "-ldl", "-lpthread"]
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with open(logf, "a") as lf:
        lf.write("$ " + " ".join(cmd) + "\n" + r.stdout)
    if r.returncode != 0:
        raise PolyccError(f"the SITL clock shim did not build: {_first_error(r.stdout) or _tail(r.stdout)} "
                          f"(full log: {logf})")
    return _app_warnings(full, app)
