"""Typed, range-checked command-line values shared by every command.

Each ``type=`` function here raises :class:`argparse.ArgumentTypeError` with the valid range
and unit, so a bad value is one line and exit code 2 (:class:`OneLineParser`), never a
traceback and never a value the rest of the chain would refuse later (for example a kappa
the on-board kernel rejects, which would leave the drone hovering).

Options that take comma-separated coordinates (``--start -2,-2.5,1``) are registered in
:data:`NEGATIVE_VALUE_OPTIONS`; :func:`join_negative_values` lets their values start with a
minus sign, which argparse would otherwise read as an option.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from typing import Callable

# Options whose value may start with '-' (coordinates, boxes).
NEGATIVE_VALUE_OPTIONS: set[str] = set()
# Options whose choices start with '-' (``--up -y``): option -> the choices.
NEGATIVE_CHOICE_OPTIONS: dict[str, set[str]] = {}
_NUMBERISH = re.compile(r"^-(\d|\.\d|inf|nan)", re.IGNORECASE)


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line naming the fix, with exit code 2."""

    def error(self, message: str):  # noqa: D102 - argparse API
        message = message.replace("%%", "%")
        self.exit(2, f"{self.prog}: error: {message}; see `{self.prog} --help`\n")


def join_negative_values(argv: list[str]) -> list[str]:
    """``['--start', '-2,-2.5,1']`` -> ``['--start=-2,-2.5,1']`` for the registered options."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if i + 1 < len(argv) and ((a in NEGATIVE_VALUE_OPTIONS and _NUMBERISH.match(argv[i + 1]))
                                  or argv[i + 1] in NEGATIVE_CHOICE_OPTIONS.get(a, ())):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def _fmt(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else f"{v:,}" if isinstance(v, int) else str(v)


def number(kind: type = float, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, unit: str = "") -> Callable[[str], float]:
    """A ``type=`` for a finite int or float in a range (closed unless ``lo_open``/``hi_open``)."""
    if lo is not None and hi is not None:
        rng = f"{'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if hi_open else ']'}"
    elif lo is not None:
        rng = f"{'>' if lo_open else '>='} {_fmt(lo)}"
    elif hi is not None:
        rng = f"{'<' if hi_open else '<='} {_fmt(hi)}"
    else:
        rng = "finite"
    what = "a whole number" if kind is int else "a number"
    unit_text = f" {unit}" if unit else ""

    def parse(text: str):
        try:
            v = kind(text.replace("_", "")) if kind is int else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}; expected {what} {rng}{unit_text}") from None
        if kind is float and not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number {rng}{unit_text}")
        bad = (lo is not None and (v <= lo if lo_open else v < lo)) or \
              (hi is not None and (v >= hi if hi_open else v > hi))
        if bad:
            raise argparse.ArgumentTypeError(f"{text!r} is out of range: expected {what} {rng}{unit_text}")
        return v

    parse.__name__ = "number"  # argparse names the type in its messages
    return parse


def numbers(count: int, what: str) -> Callable[[str], tuple[float, ...]]:
    """A ``type=`` for ``count`` comma-separated finite numbers (``what`` describes them)."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            vals = tuple(float(x) for x in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {what}") from None
        if len(vals) != count:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {what}, got {len(vals)} numbers")
        if not all(math.isfinite(v) for v in vals):
            raise argparse.ArgumentTypeError(f"{text!r}: expected finite numbers, {what}")
        return vals

    parse.__name__ = "numbers"
    return parse


def add_point_option(parser, *names: str, **kw) -> None:
    """An ``X,Y,Z`` option in metres whose value may be negative."""
    import numpy as np

    parse = numbers(3, "x,y,z in metres, e.g. -2,-2.5,1")
    kw.setdefault("metavar", "X,Y,Z")
    parser.add_argument(*names, type=lambda t: np.array(parse(t)), **kw)
    NEGATIVE_VALUE_OPTIONS.update(n for n in names if n.startswith("--"))


def main_argv(argv: list[str] | None) -> list[str]:
    return join_negative_values(list(sys.argv[1:] if argv is None else argv))


def add_parallel_options(parser) -> None:
    """``--jobs N`` and ``--dask ADDRESS``: where the pipeline's tasks run (never what they give)."""
    from polycc.parallel import available_cores

    g = parser.add_argument_group("where it runs (the result is the same for any choice)")
    g.add_argument("--jobs", type=number(int, 1, 4096, unit="processes"), default=None, metavar="N",
                   help="local worker processes for occupancy slabs, cover tiles and budget candidates, 1..4096 "
                        f"(default: every core this process may use, here {available_cores()})")
    g.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run the same task graph on Dask distributed instead: tcp://HOST:PORT of a running "
                        "scheduler (each worker needs this polycc installed), or local:N for a local cluster of N "
                        "worker processes; needs pip install 'polycc[dask]' (default: not used)")
