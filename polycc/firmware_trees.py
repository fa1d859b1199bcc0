"""Crazyflie firmware source trees given by the user: a folder, or a tarball extracted once into the cache.

Two kinds (both with a one-line :class:`~polycc.errors.PolyccError` naming the fix when the folder is
not one):

* ``"upstream"`` -- bitcraze/crazyflie-firmware with its submodules, for the Cortex-M4 build of the app
  (:mod:`polycc.ground.flash`): ``tools/make/oot.mk`` and the vendor submodules must be there.
* ``"sitl"`` -- the CrazySim SITL fork (llanesc/crazyflie-firmware ``sitl-release``), for the native
  ``cf2`` (:mod:`polycc.sim.firmware.build`): ``sitl_make/CMakeLists.txt`` with its ``cf2`` target, the
  POSIX FreeRTOS port and the SITL drivers.

A tarball (``.tar.xz``, ``.tar.gz``, ``.tar``) is extracted once into
``<cache>/firmware/trees/<sha256[:16]>/`` (:func:`polycc.resources.cache_dir`) under a file lock and
never written to afterwards: builds only read it (symlinks, ``include()``, out-of-tree objects).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import tarfile
import tempfile
from pathlib import Path

from polycc import resources
from polycc.errors import PolyccError

SITL_MARKERS = (
    "sitl_make/CMakeLists.txt",
    "src/init/main_sitl.c",
    "src/hal/src/socketlink.c",
    "src/hal/src/sensors_sitl.c",
    "src/modules/src/power_distribution_sitl.c",
    "src/modules/src/app_handler.c",
    "vendor/FreeRTOS/portable/ThirdParty/GCC/Posix/port.c",
    "tools/make/versionTemplate.py",
)
# Upstream submodules the ARM build needs (folder -> a file or folder that is there when it is checked out).
UPSTREAM_SUBMODULES = {
    "vendor/FreeRTOS": "vendor/FreeRTOS/include/FreeRTOS.h",
    "vendor/CMSIS": "vendor/CMSIS/CMSIS/Core/Include",
    "vendor/libdw1000": "vendor/libdw1000/inc",
}
TARBALL_SUFFIXES = (".tar.xz", ".txz", ".tar.gz", ".tgz", ".tar.bz2", ".tar")


class locked:
    """Exclusive ``flock`` on ``path`` for the duration of a with-block (several processes may build)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def __enter__(self) -> "locked":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o644)
        fcntl.flock(self.fd, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc) -> None:
        fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def is_tarball(path: str | os.PathLike) -> bool:
    p = Path(path)
    return p.is_file() and p.name.endswith(TARBALL_SUFFIXES)


def extract_tarball(tarball: str | os.PathLike, log=None) -> Path:
    """Extract ``tarball`` once into the cache and return its single top-level folder."""
    tarball = Path(tarball)
    if not tarball.is_file():
        raise PolyccError(f"{tarball}: no such file")
    digest = sha256_file(tarball)[:16]
    root = resources.cache_dir("firmware", "trees")
    dest = root / digest
    with locked(root / f".{digest}.lock"):
        if not dest.is_dir():
            if log:
                log(f"extracting {tarball.name} into {dest}")
            tmp = Path(tempfile.mkdtemp(prefix=f".{digest}-", dir=root))
            try:
                try:
                    with tarfile.open(tarball) as tf:
                        tf.extractall(tmp, filter="tar")
                except (tarfile.TarError, EOFError, OSError) as exc:
                    raise PolyccError(f"{tarball}: cannot extract ({exc}); pass the firmware tree folder or an "
                                      "intact .tar.xz") from None
                os.rename(tmp, dest)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
    tops = [p for p in dest.iterdir() if not p.name.startswith(".")]
    if len(tops) != 1 or not tops[0].is_dir():
        raise PolyccError(f"{tarball}: expected one top-level folder in the archive, found {len(tops)}")
    return tops[0]


def looks_like_sitl(tree: Path) -> bool:
    return (tree / "sitl_make" / "CMakeLists.txt").is_file() and (tree / "src" / "init" / "main_sitl.c").is_file()


def check_sitl_tree(tree: str | os.PathLike) -> Path:
    """The resolved root of a CrazySim SITL tree, or a one-line error with the first missing file."""
    tree = Path(tree).expanduser().resolve()
    if not tree.is_dir():
        raise PolyccError(f"{tree}: no such folder; pass the CrazySim SITL firmware (llanesc/crazyflie-firmware "
                          "sitl-release) checkout or its tarball")
    for rel in SITL_MARKERS:
        if not (tree / rel).is_file():
            hint = (" (this is the upstream bitcraze firmware: use it for `polycc flash`)"
                    if (tree / "tools" / "make" / "oot.mk").is_file() else "")
            raise PolyccError(f"{tree}: not a CrazySim SITL firmware tree (missing {rel}){hint}; pass the "
                              "llanesc/crazyflie-firmware sitl-release checkout (with submodules) or its tarball")
    text = (tree / "sitl_make" / "CMakeLists.txt").read_text(errors="replace")
    if "add_executable(cf2" not in text:
        raise PolyccError(f"{tree}: sitl_make/CMakeLists.txt has no cf2 target; not a CrazySim SITL tree")
    return tree


def check_upstream_tree(tree: str | os.PathLike) -> Path:
    """The resolved root of an upstream firmware tree with its submodules, or a one-line error."""
    tree = Path(tree).expanduser().resolve()
    if not (tree / "tools" / "make" / "oot.mk").is_file():
        raise PolyccError(f"{tree}: no crazyflie-firmware tree here (tools/make/oot.mk missing); "
                          "git clone --recursive https://github.com/bitcraze/crazyflie-firmware and pass its path "
                          "(or its tarball)")
    if looks_like_sitl(tree):
        raise PolyccError(f"{tree}: this is the CrazySim SITL fork, whose Cortex-M4 build fails in its own "
                          "stabilizer.c (implicit usddeck calls); pass the upstream bitcraze/crazyflie-firmware tree "
                          "(use the SITL fork with `polycc sim --firmware`)")
    missing = [name for name, probe in UPSTREAM_SUBMODULES.items() if not (tree / probe).exists()]
    if missing:
        raise PolyccError(f"{tree}: submodules {', '.join(missing)} are empty; run "
                          "`git submodule update --init --recursive` in the firmware tree")
    return tree


def resolve_tree(source: str | os.PathLike, kind: str, log=None) -> Path:
    """A firmware tree folder from ``source`` (a folder, or a tarball extracted into the cache), checked
    for ``kind`` ``"sitl"`` or ``"upstream"``."""
    src = Path(source).expanduser()
    if kind not in ("sitl", "upstream"):
        raise ValueError(f"kind must be 'sitl' or 'upstream', not {kind!r}")
    if src.is_file():
        if not is_tarball(src):
            raise PolyccError(f"{src}: not a firmware folder or tarball (.tar.xz, .tar.gz, .tar); pass the firmware "
                              "tree")
        src = extract_tarball(src, log)
    return check_sitl_tree(src) if kind == "sitl" else check_upstream_tree(src)


def tree_identity(tree: Path, dirs: tuple[str, ...]) -> str:
    """Content hash of the files under ``dirs`` of ``tree`` (names, symlink targets and bytes)."""
    h = hashlib.sha256()
    for d in dirs:
        for root, subdirs, files in os.walk(tree / d):
            subdirs.sort()
            for name in sorted(files):
                p = Path(root) / name
                h.update(p.relative_to(tree).as_posix().encode() + b"\0")
                if p.is_symlink():
                    h.update(b"L" + os.readlink(p).encode())
                elif p.is_file():
                    h.update(sha256_file(p).encode())
    return h.hexdigest()
