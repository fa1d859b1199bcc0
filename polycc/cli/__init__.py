"""The `polycc` command line: one sub-command per module in :mod:`polycc.cli`.

Each command module exposes ``register(subparsers)``; it adds its parser and sets
``func`` to a callable taking the parsed arguments and returning an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from polycc.cli.argtypes import OneLineParser, main_argv
from polycc.errors import PolyccError
from polycc.version import __version__

# Order is the order shown by `polycc --help`.
COMMAND_MODULES = [
    "demo_scene",
    "info",
    "align",
    "export",
    "view",
    "voxelize",
    "cover",
    "verify",
    "build",
    "plan",
    "sim",
    "sim_device",
    "swarm_sim",
    "swarm_fly",
    "fly",
    "flash",
]


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="polycc",
        description=(
            "Turn a 3D Gaussian Splatting scene into a certified polytope obstacle cover "
            "and Crazyflie firmware. All lengths are metres in the world frame."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"polycc {__version__}")
    sub = parser.add_subparsers(title="commands", dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"polycc.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(main_argv(argv))
    except SystemExit as exc:  # --help, --version, or a one-line usage error (OneLineParser)
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except PolyccError as exc:
        print(f"polycc {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"polycc {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
