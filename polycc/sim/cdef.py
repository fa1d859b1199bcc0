"""cffi declarations generated from the C headers themselves, never copied by hand.

:func:`header_cdef` turns a header into what ``cffi.FFI.cdef`` accepts: comments and
preprocessor lines are removed (the ``#ifdef __cplusplus`` blocks with their contents),
``_Static_assert`` lines are dropped, and integer-valued ``#define NAME 12u`` constants become
``#define NAME ...`` so that cffi reads their values from the compiled code. Typedefs and
function prototypes pass through unchanged, so a struct changed in the header is changed in the
bindings too.
"""

from __future__ import annotations

import re
from pathlib import Path

_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
_INT_DEFINE = re.compile(r"#\s*define\s+([A-Z_][A-Z0-9_]*)\s+\(?(0[xX][0-9a-fA-F]+|\d+)[uUlL]*\)?\s*$")


def header_cdef(path: str | Path, constants: bool = True) -> str:
    """The cffi ``cdef`` text of one header (see the module docstring)."""
    text = _COMMENT.sub("", Path(path).read_text())
    out: list[str] = []
    skip = 0  # depth inside an `#ifdef __cplusplus` block
    depth = 0
    cpp_depth: list[int] = []
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("#"):
            d = line[1:].strip()
            if d.startswith(("if", "ifdef", "ifndef")):
                depth += 1
                if "__cplusplus" in d:
                    cpp_depth.append(depth)
                    skip += 1
            elif d.startswith("endif"):
                if cpp_depth and cpp_depth[-1] == depth:
                    cpp_depth.pop()
                    skip -= 1
                depth -= 1
            elif constants and not skip:
                m = _INT_DEFINE.match(line)
                if m:
                    out.append(f"#define {m.group(1)} ...")
            continue
        if skip or not line or line.startswith("_Static_assert"):
            continue
        out.append(raw)
    return "\n".join(out) + "\n"


def headers_cdef(*paths: str | Path, constants: bool = True) -> str:
    return "".join(header_cdef(p, constants) for p in paths)
