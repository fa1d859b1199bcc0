"""The one place that finds what polycc ships and where it builds.

Shipped files (package data in the wheel, plain folders in a checkout):

* :func:`firmware_app` -- the Crazyflie out-of-tree app (``Makefile``, ``app-config``, ``Kbuild``,
  ``src/``). In a checkout it is ``firmware_app/`` beside the package; in a wheel it is installed
  as ``polycc/firmware_app/`` (``pyproject.toml`` maps it in).
* :func:`templates` -- the jinja2 templates of the generated C (``polycc/codegen/templates``).
* :func:`shims` -- firmware API shims for the host build (``polycc/sim/shims``).
* :func:`arm_harness` -- the bare-metal Cortex-M4 test harness (``polycc/sim/arm``).

Builds (cffi extensions, ARM ELFs, firmware) go to :func:`cache_dir`: ``$POLYCC_CACHE_DIR``, else
``$XDG_CACHE_HOME/polycc``, else ``~/.cache/polycc`` -- never into the installed package or the
checkout.
"""

from __future__ import annotations

import os
from pathlib import Path

from polycc.errors import PolyccError

PACKAGE = Path(__file__).resolve().parent


def firmware_app() -> Path:
    """The ``firmware_app/`` folder (the Bitcraze out-of-tree layout)."""
    for cand in (PACKAGE / "firmware_app", PACKAGE.parent / "firmware_app"):
        if (cand / "src" / "polycc_kernel.c").is_file():
            return cand
    raise PolyccError(f"the Crazyflie app sources (firmware_app/) are missing from {PACKAGE}; reinstall polycc "
                      "(pip install --force-reinstall polycc)")


def firmware_src() -> Path:
    """``firmware_app/src``: the app, the portable kernel and the scene layout header."""
    return firmware_app() / "src"


def templates() -> Path:
    return PACKAGE / "codegen" / "templates"


def shims() -> Path:
    return PACKAGE / "sim" / "shims"


def arm_harness() -> Path:
    return PACKAGE / "sim" / "arm"


def cache_dir(*parts: str) -> Path:
    """A folder under the build cache (created)."""
    base = os.environ.get("POLYCC_CACHE_DIR")
    if not base:
        xdg = os.environ.get("XDG_CACHE_HOME")
        base = str(Path(xdg) / "polycc") if xdg else str(Path.home() / ".cache" / "polycc")
    path = Path(base).joinpath(*parts)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PolyccError(f"{path}: cannot create the build cache ({exc.strerror or exc}); set POLYCC_CACHE_DIR "
                          "to a writable folder") from None
    return path
